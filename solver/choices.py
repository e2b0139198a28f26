"""Names the command line offers before any solver code (numpy, numba) loads: the
solvers, the motion predictors, and the devices of the Vive recordings. The modules that
implement them import these from here."""

SOLVERS = ("analytic", "dls", "paper")
DEFAULT_SOLVER = "analytic"
PREDICTORS = ("velocity", "slimevr", "posecast")  # solver.prediction's kinds
VIVE_DEVICES = ("head", "hip", "left_hand", "right_hand", "left_forearm", "right_forearm",
                "left_foot", "right_foot", "left_knee", "right_knee", "chest")
