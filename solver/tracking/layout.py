"""Where each value lives in an avatar's body constants (``shape``, from its calibration)
and in its tracking state (``state``): flat float64 rows, so that every avatar of a batch
is one row of two arrays and the compiled kernels take them whole."""

from __future__ import annotations

from posecast.solver.tracking.devices import DEVICES

ND = len(DEVICES)

# --- shape: the avatar's body, fixed at calibration --------------------------------------
S_G0_HEAD = 0  # (4) the head joint's global rotation in the canonical pose
S_G0_PELVIS = 4  # (4)
S_FLAT_FOOT = 8  # (2 x 4) each foot flat on the floor, facing +z
S_HAND_DOWN = 16  # (2 x 4) each hand of an arm hanging at the side, facing +z
S_HEAD_TO_PELVIS = 24  # (3) pelvis - head joint, standing upright, body axes
S_HIP = 27  # (2 x 3) each hip joint - pelvis, body axes
S_SHOULDER = 33  # (2 x 3) each shoulder (upper arm joint) - head joint, body axes
S_LEG = 39  # hip joint to ankle, straight leg (m)
S_ARM = 40  # shoulder to wrist, straight arm (m)
S_ANKLE = 41  # the ankle joint's height above the floor, standing (m)
S_FLOOR = 42  # the floor's height (m)
S_STAND_HEAD = 43  # the head joint's height standing (m)
S_STAND_PELVIS = 44  # the pelvis's height standing (m)
S_FEET0 = 45  # (2 x 3) where the feet stood at calibration
S_YAW0 = 51  # the body's heading at calibration (rad about +y, 0 = facing +z)
S_NAIVE = 52  # 1: the naive baseline (pelvis under the head, legs straight down)
S_MODEL = 53  # the body model's constants (body_model.FIELDS, in order):
S_DROP_BACK = S_MODEL
S_YAW_SLACK = S_MODEL + 1
S_YAW_RATE = S_MODEL + 2
S_NECK = S_MODEL + 3
S_STEP_DIST = S_MODEL + 4
S_STEP_TIME = S_MODEL + 5
S_LEAD = S_MODEL + 6
S_CROUCH = S_MODEL + 7
S_REACH = S_MODEL + 8
SHAPE_SIZE = S_MODEL + 9

# --- state: what the tracking remembers from frame to frame -----------------------------
K_T = 0  # the last frame's time (s)
K_INIT = 1  # 0 until the first frame
K_PEL_YAW = 2  # the body model's pelvis heading (rad)
K_PEL_ADAPT = 3  # (3) measured pelvis - the model's, body axes (learned while tracked)
K_PEL_PREV = 6  # (3) the last pelvis position
K_PEL_VEL = 9  # (3) its velocity, smoothed (m/s)
K_FEET = 12  # per foot (2 x FOOT_STRIDE):
F_POS = 0  # (3) where the model's foot is
F_YAW = 3  # its heading
F_SWING = 4  # 1 while stepping
F_START = 5  # (3) where the step started
F_YAW0 = 8  # the heading it started with
F_T0 = 9  # when it started (s)
F_LEN = 10  # how long it lasts (s)
F_ROT = 11  # (4) the model's foot rotation
F_ROT0 = 15  # (4) its rotation when the step started
FOOT_STRIDE = 19
K_DEV = K_FEET + 2 * FOOT_STRIDE  # per device (ND x DEV_STRIDE):
D_OUT = 0  # (7) the target given last frame
D_MEAS = 7  # (7) the last measured pose
D_VEL = 14  # (3) its velocity, smoothed (m/s)
D_LOST = 17  # seconds since it was lost (0 while tracked)
D_BACK = 18  # seconds since it came back (large once settled)
D_OFF = 19  # (7) target - measured when it came back: fades out (position, rotation)
D_HELD = 26  # (7) the measured pose relative to its anchor, kept while tracked
D_SEEN = 33  # 1 once it has been measured
D_BLEND = 34  # how long (s) its return blend lasts: longer for a larger offset
DEV_STRIDE = 35
STATE_SIZE = K_DEV + ND * DEV_STRIDE
