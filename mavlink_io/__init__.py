"""MAVLink I/O for azimuthd: connections, heartbeat, rate requests, decoding to typed SI samples.

MAVLink 2 is selected here, before anything imports pymavlink's mavutil (it reads MAVLINK20 at
import time to pick the protocol version of ``mavutil.mavlink``).
"""
import os as _os

_os.environ["MAVLINK20"] = "1"
