"""What people open: the report, the web viewer, the WMS mapfile and a local file server."""
