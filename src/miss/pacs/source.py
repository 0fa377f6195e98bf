"""A PACS series as a job's source: ``miss convert dicomweb:STUDY/SERIES``.

The series is retrieved into a temporary folder and read there by the confined reader,
as the server reads an upload (:mod:`miss.io.confined`): what a PACS sends is untrusted
on the command line too.
"""

from __future__ import annotations

import tempfile
from dataclasses import dataclass
from pathlib import Path

from miss.errors import BadParameter
from miss.pacs import client
from miss.pacs.server import PacsServer, configured_servers
from miss.spec import Loaded

PREFIX = "dicomweb:"
#: Largest series the command line retrieves, bytes (as the server's default upload limit).
MAX_BYTES = 2048 << 20


def parse(text: str) -> tuple[str, str] | None:
    """``dicomweb:STUDY/SERIES`` -> (study, series); None for anything else."""
    if not text.startswith(PREFIX):
        return None
    study, sep, series = text[len(PREFIX) :].partition("/")
    if not sep:
        raise BadParameter(
            f"{text!r}: write a PACS series as dicomweb:STUDY_UID/SERIES_UID "
            "('miss pacs search' lists them)."
        )
    return client.check_uid(study, "study"), client.check_uid(series, "series")


def pick_server(name: str | None = None) -> PacsServer:
    """The PACS ``name`` (the first configured when None), from the environment."""
    servers = configured_servers()
    if not servers:
        raise BadParameter(
            "no PACS configured; set MISS_PACS_URL to its DICOMweb root (e.g. "
            "http://127.0.0.1:8042/dicom-web) and MISS_PACS_AUTH_FILE to its credentials."
        )
    if name is None:
        return servers[0]
    for server in servers:
        if server.name == name:
            return server
    raise BadParameter(f"no PACS named {name!r}; configured: {', '.join(s.name for s in servers)}.")


@dataclass(frozen=True)
class PacsSeries:
    """One series on a PACS, read as a volume (the server's name, study, series UIDs)."""

    server: PacsServer
    study: str
    series: str

    def load(self, labels: bool) -> Loaded:
        """Retrieve the series into a temporary folder and read it as an upload is read."""
        from miss.io.confined import Limits, parse_upload, probe

        if labels:
            raise BadParameter(
                "a PACS series has no label map on the command line; use --level, or import "
                "the series with its segmentation in the web system."
            )
        instances = client.list_instances(self.server, self.study, self.series, 5000)
        with tempfile.TemporaryDirectory(prefix="miss-pacs-") as tmp:
            work = Path(tmp)
            (work / "unzipped").mkdir()
            client.retrieve_series(
                self.server, self.study, self.series, work / "unzipped", MAX_BYTES,
                len(instances),
            )  # fmt: skip
            parsed = parse_upload(work, "pacs-series", probe(work), Limits())
        assert parsed.volume is not None
        return Loaded(parsed.volume, title=f"{self.server.name} series {self.series}")
