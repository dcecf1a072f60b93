"""The reference model (kinematics, IMU, range), shared by every part of the toolkit."""

from uwbimu.models import quaternion, state, reference, imu  # noqa: F401
from uwbimu.models.reference import GRAVITY, G_WORLD  # noqa: F401
