"""overtake.server.sim: the simulation core (traffic, sensors, rewards, presets, kernels)."""
