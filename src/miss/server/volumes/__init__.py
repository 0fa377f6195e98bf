"""Volumes in the server: ingest (the one door for an upload, an import or the demo),
streamed uploads, label maps, slice imaging and the volume summary."""
