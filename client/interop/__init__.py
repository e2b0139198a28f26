"""Into and out of other tools: recording a room to a file and replaying it, exporting
BVH, and VMC (OSC) for VSeeFace, Warudo and the like.

Imports protocol/, solver/ and client.session; never cli or bench.
"""
