"""The contract between overtake's parts: environment ids now; wire messages as they come."""

from .envs import HIGHWAY_ENV_ID, register_environments

__all__ = ["HIGHWAY_ENV_ID", "register_environments"]
