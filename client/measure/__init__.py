"""Measuring what people see: latency accounting stage by stage, the paper's video
latency tool (OpenCV), the display error of a viewer's playout, and the plots.

Imports protocol/, solver/, client.sources, client.session and client.viewer (the
display error replays a viewer's playout); never cli or bench.
"""
