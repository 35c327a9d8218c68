"""What Rerun shows of overtake: recording sinks (an ``.rrd`` file, a viewer over gRPC, a web
viewer) and the views of world frames that servers and spectators both log.

It sits beside :mod:`overtake.protocol` (the only part of the project it imports): the server,
which records its arenas itself, and the client's spectators draw the same view, and neither
may import the other. Importing this package loads nothing; ``rerun`` loads when a recording
opens.
"""
