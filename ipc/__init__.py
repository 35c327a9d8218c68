"""How overtake's processes reach each other: the Zenoh session with its settings and its
diagnosis of a failed connection (transport, endpoints), and, for a trainer on the server's
own host, the shared-memory segment (shared_memory) and the futex doorbell that wakes its
reader (doorbell).

The messages these carry are the contract's (overtake.protocol); this package is the mechanism
and imports of the project only the contract. Importing it loads nothing heavy: each module
loads Zenoh or libc when it is imported itself.
"""
