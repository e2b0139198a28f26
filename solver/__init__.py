"""Kinematics core: skeletons, forward kinematics, calibration, IK solvers, motion readers
and accuracy metrics. Pure: numpy arrays in, numpy arrays out; no sockets, no GL."""
