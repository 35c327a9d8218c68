"""What a trainer imports: environment registration, baseline drivers, and (soon) the remote
environment. Importing it registers ``overtake/Highway-v0`` without importing the simulator."""

from overtake.protocol import HIGHWAY_ENV_ID, register_environments

from .drivers import RandomDriver, RuleDriver, RuleDriverConfig

register_environments()

__all__ = ["HIGHWAY_ENV_ID", "RandomDriver", "RuleDriver", "RuleDriverConfig"]
