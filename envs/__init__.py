"""The environments over an engine: the Gymnasium single and vector faces (:mod:`.faces`), the
PettingZoo face (:mod:`.parallel_face`), highway-env's interface (:mod:`.highway_env_like`), the
rows a face reads (:mod:`.step_rows`) and the Gymnasium ids (:mod:`.registry`).

Written once over an engine that is the simulator in this process (overtake.server.local) or a
remote group (overtake.client.wire.remote); imports of the project only the contract
(overtake.protocol). Importing this package loads Gymnasium; it registers nothing
(``import overtake.client`` does).
"""

from .registry import HIGHWAY_ENV_ID, REMOTE_HIGHWAY_ENV_ID, register_environments

__all__ = ["HIGHWAY_ENV_ID", "REMOTE_HIGHWAY_ENV_ID", "register_environments"]
