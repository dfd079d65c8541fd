"""The `rmmdet` command-line tool."""
