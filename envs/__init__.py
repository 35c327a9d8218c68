"""The environments over an engine: the Gymnasium single and vector faces (faces), the
PettingZoo face (parallel_face), highway-env's interface (highway_env_like), the rows a face
reads (step_rows) and the Gymnasium ids (registry).

Written once over an engine that is the simulator in this process (overtake.server.engine.local) or
a remote group (overtake.client.wire.remote); imports of the project only the contract
(overtake.protocol). Importing this package loads Gymnasium; it registers nothing
(``import overtake.client`` does).
"""

from .registry import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, register_environments

__all__ = ["HIGHWAY_ENV_ID", "REMOTE_HIGHWAY_ENV_ID", "register_environments"]
