"""overtake.protocol: the wire contract (messages, codec, keys, errors, its description)."""
