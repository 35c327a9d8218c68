"""The environment faces over a remote simulator: Gymnasium's single and vector environments
(``overtake/RemoteHighway-v0``: :mod:`.remote_gym`) and PettingZoo's Parallel API, several
learning cars on one road (:mod:`.parallel_env`). Their in-process twins are the server's
(``overtake.server.engine.env``, ``overtake.server.engine.parallel_env``)."""
