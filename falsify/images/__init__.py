"""Images without an imaging library: PNG read and write, pictures of scans, overlays."""
