"""Every `posecast bench ...` and the demo: their harnesses, the network emulator that
puts a real link between processes, and the Redis process the cluster benches start.

May import any other client package; nothing imports bench but cli.
"""
