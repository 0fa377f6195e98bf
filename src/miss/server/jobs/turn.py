"""The viewer's turn: once a job's model can be drawn, the job holds back its other work
until a physician's viewer that follows the job has drawn it, for at most :data:`HOLD`
seconds.

After its GLB (or its levels of detail) a job still writes the other formats, measures
the error, and the queue warms up the next spare worker: seconds of work at the lowest
priority. Where the browser shares the server's machine (``make run`` on a workstation,
a desktop without a GPU drawing in software) that work still slowed the model's first
frame about twofold. So the job waits for the viewer's word, and only while a viewer is
there to give it:

- the model page's event stream (``GET /api/models/{id}/events?draws=1``; other
  followers, such as scripts, leave ``draws`` out) touches ``models/<id>/.watched`` each
  time it looks at the job (:func:`watching`): a viewer follows the job while the file
  is fresh (:data:`FRESH` seconds);
- the page says when the GPU has finished the first frame with the model
  (``POST /api/models/{id}/shown``), which creates ``models/<id>/.shown`` (:func:`shown`);
- the worker, after recording the file a viewer draws, waits while :func:`held`: a
  viewer follows, has not drawn it yet, and :data:`HOLD` seconds have not passed;
  the queue starts the next spare only once the job is no longer held.

Nobody watching (the API, ``miss convert``, a closed tab) and nothing waits. Files rather
than the database: a stat every few milliseconds costs nothing, and the worker and the
server share the data folder however many server processes there are.
"""

from __future__ import annotations

import contextlib
import os
import time
from pathlib import Path

#: A file touched by the job's event stream while a viewer follows the job.
WATCHED = ".watched"
#: A file created when a viewer has drawn the job's model.
SHOWN = ".shown"
#: Seconds a job waits at most for the viewer's word.
HOLD = 1.0
#: Seconds after its last touch that ``.watched`` still says a viewer follows the job
#: (the event stream touches it at least every ``EVENT_POLL``, 0.1 s).
FRESH = 2.0
#: Seconds between the worker's looks for ``.shown``.
LOOK = 0.01


def watching(folder: Path) -> None:
    """A viewer follows the job of ``folder`` now. Best effort, and never creating the
    folder (the job's runner does; a deleted model's stays deleted): a folder that is
    not there, or cannot be written, makes no viewer wait."""
    with contextlib.suppress(OSError):
        (folder / WATCHED).touch()


def shown(folder: Path) -> None:
    """A viewer has drawn the model of ``folder``."""
    with contextlib.suppress(OSError):
        (folder / SHOWN).touch()


def forget(folder: Path) -> None:
    """A new attempt at the job: an earlier attempt's viewer has drawn nothing of it."""
    with contextlib.suppress(OSError):
        (folder / SHOWN).unlink(missing_ok=True)


def done(folder: Path) -> None:
    """The job has ended (done or failed): nothing waits for a viewer any more, and neither
    file stays in the model's folder. Called where the row says so
    (:class:`~miss.server.jobs.state.JobState`), and by a viewer's event stream as it ends,
    which may have touched ``.watched`` between the row's change and its reading of it."""
    for name in (WATCHED, SHOWN):
        with contextlib.suppress(OSError):
            (folder / name).unlink(missing_ok=True)


def held(folder: Path, since: float, now: float | None = None) -> bool:
    """Whether the job of ``folder``, drawable since ``since`` (``time.time()``), waits for
    its viewer: one follows it (``.watched`` touched within :data:`FRESH` s), has not
    drawn it (no ``.shown``), and :data:`HOLD` s have not passed."""
    now = time.time() if now is None else now
    if now - since >= HOLD or (folder / SHOWN).exists():
        return False
    try:
        touched = os.stat(folder / WATCHED).st_mtime
    except OSError:
        return False
    return now - touched < FRESH


def wait_turn(folder: Path, since: float) -> float:
    """Wait while :func:`held`; returns the seconds waited (0 when it was not)."""
    if not held(folder, since):
        return 0.0
    start = time.monotonic()
    while held(folder, since):
        time.sleep(LOOK)
    return time.monotonic() - start
