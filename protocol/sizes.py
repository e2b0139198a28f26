"""The protocol's size limits and naming rule, as plain constants: what the command line
shows in its help before any of the protocol's code (pydantic, numpy) loads.
``protocol.validation`` enforces them."""

# Any message. The largest legitimate one is a full roster: ~2.5 KB per 60-joint avatar,
# so 1 MiB holds a room of a few hundred avatars.
MAX_MESSAGE_BYTES = 1 << 20
# What a server accepts from a client (hello, tracker frame, calibrate, ping, leave,
# viewer report): a 10-device tracker frame is ~340 bytes, a hello with the longest token
# ~1200 bytes, the largest viewer report (128 rows, 4 shown poses of 53 joints) ~5 KB.
MAX_CLIENT_MESSAGE_BYTES = 8192
MAX_JOINTS = 256  # the MakeHuman rig has 53, large BVH skeletons ~100
MAX_AVATARS = 1024  # per roster or batch message
MAX_NAME_CHARS = 64  # room, display and joint names
MAX_TOKEN_CHARS = 1024  # a signed join token (JWT, server.auth) is ~250-800 characters
MAX_TEXT_CHARS = 1024  # error messages, leave reasons
MAX_POSITION_M = 1000.0  # tracked spaces are metres across; 1e300 would overflow the solver
MAX_RATE_HZ = 1000.0
# a solved frame's times travel as float32 ages before its sending (protocol 4): a real
# one is milliseconds old, a replayed one at most its recording's length
MAX_AGE_S = 1e6
QUAT_NORM_TOLERANCE = 1e-3  # |norm - 1| accepted, then normalised
MAX_INT = 2**63 - 1  # ids and sequence numbers fit an int64

# room names end up in URLs, command lines and logs: keep them plain, and say the rule in
# words (a regex in an error message helps nobody)
ROOM_NAME_RULE = ("room names are 1-64 letters, digits, '-', '_' or '.', starting with a "
                  "letter or digit")
