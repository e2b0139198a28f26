"""From whatever devices a player has, at any moment, to the solver's targets.

- ``devices``: the roles, their solver slots, tracker sets (``--devices``).
- ``dropouts``: simulated tracking losses (``--dropouts``).
- ``shape``: the body constants the model needs, from a calibration.
- ``pelvis``, ``legs``: the body model for a pelvis or feet without a tracker.
- ``fill``: per frame, tracked devices, carried lost ones and the model -> targets.
- ``rows``: avatars' tracking as rows of arrays (what the server and eval use).
"""
