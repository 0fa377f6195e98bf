"""A hospital's PACS over DICOMweb: find studies (QIDO-RS), bring a series in (WADO-RS),
send a model back into the patient's study (STOW-RS), with ``dicomweb-client``.

- :mod:`miss.pacs.server`: :class:`PacsServer` (name, DICOMweb root, credentials file)
  and the configured list;
- :mod:`miss.pacs.client`: the three transactions, with everything the PACS sends
  treated as untrusted (bodies capped as they arrive, answers checked, pixels decoded
  only by the confined reader);
- :mod:`miss.pacs.stl`: a model as DICOM Encapsulated STL instances;
- :mod:`miss.pacs.source`: a PACS series as a job's source (``miss convert
  dicomweb:STUDY/SERIES``).
"""

from miss.pacs.server import PacsServer, configured_servers

__all__ = ["PacsServer", "configured_servers"]
