"""The room in the player's headset (``posecast play --hmd`` and ``--hmd-out DIR``).

Modules, in the order a headset frame uses them:
- ``stereo``: each eye's camera from the headset's pose, its eye-to-head transform and
  projection, as SteamVR gives them; a Vive's values for where there is no SteamVR.
  Pure.
- ``local_body``: the player's own avatar calibrated and solved on the player's machine,
  with the server's solver and calibration, from the very poses the frame is drawn with.
- ``room``: what the headset shows besides avatars: the mirror (the scene rendered once
  more, reflected) and the floor-anchored and head-anchored text (names, the HUD).
- ``displays``: where frames go: SteamVR's compositor (``compositor``: openvr, the only
  module here that talks to it), PNG files side by side, or nowhere (a benchmark).
- ``view``: the frame loop, on a thread of its own that owns the GL context: the
  compositor blocks it until the next frame is due, never the asyncio session.
- ``session``: the loop run beside a player: the headset's spectator connection (the
  others, through the viewer's snapshot buffer and prediction), its reports, its HUD.

Imports protocol/, solver/, server.avatars (the server's own solver state, so that the
local body and the server's agree), client.session, client.sources, client.viewer and
client.measure; never cli or bench.
"""
