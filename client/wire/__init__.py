"""The wire, the trainer's side of it: one Zenoh session with this trainer's liveliness token
(:mod:`.connection`), the arena groups opened through it (:mod:`.remote`), Steps through shared
memory on the server's host (:mod:`.shm_channel`), read-only spectators (:mod:`.world_feed`),
and the commands that watch servers (``overtake-status``: :mod:`.status`;
``overtake-spectate``: :mod:`.spectate`)."""
