"""Steps through shared memory between a server and a trainer on one host."""
