"""End to end: real server, router, trainer and example processes on 127.0.0.1 (compose too)."""
