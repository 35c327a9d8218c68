"""The overtake simulator: the numpy core (``overtake.server.sim``), the in-process Gymnasium
environments (``overtake.server.engine.env``) and the Zenoh service around them
(``overtake-server``).

Importing it registers nothing and loads nothing but this docstring; ``import overtake.client``
registers the Gymnasium ids.
"""
