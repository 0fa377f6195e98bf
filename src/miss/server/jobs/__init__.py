"""Jobs: a queue of threads in the server (``queue``), each supervising one worker process
at a time (``process``, which runs ``worker``); a job's life in its database row
(``state``) and the viewer's turn (``turn``)."""

from miss.server.jobs.process import Runner, Running, WorkerProcess, crash_reason, read_log
from miss.server.jobs.queue import JobQueue

__all__ = ["JobQueue", "Runner", "Running", "WorkerProcess", "crash_reason", "read_log"]
