"""overtake-server around the engine: the loop, what arrives and what goes out, the arena
groups and the trainers' ledger, the requests' simulators, access control and the recorder."""
