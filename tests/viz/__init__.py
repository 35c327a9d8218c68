"""overtake.viz: Rerun recordings, their layouts and what the viewer draws."""
