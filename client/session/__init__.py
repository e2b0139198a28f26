"""A client's session with a server: connecting (clock sync, reconnects, redirects,
TLS), the player that streams its poses, the spectator that receives a room.

Imports protocol/, client.sources and the latency accounting (client.measure.latency);
never cli, bench or the viewer.
"""
