"""overtake.server: the simulator server's parts (arena groups); sim/ is the simulation core."""
