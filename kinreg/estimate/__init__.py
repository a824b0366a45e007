"""Pure estimation over in-memory types: no files, no processes."""
