"""The overtake simulator: the numpy core (``overtake.server.sim``) and what serves it."""

from overtake.protocol import register_environments

register_environments()
