"""Zenoh key layout: the one place keys are spelled.

Keys are by role, not by producer, so that swapping the simulator for the real car is only a
matter of which publisher runs:

| key                              | message        | published by              | consumed by           |
|----------------------------------|----------------|---------------------------|-----------------------|
| racecav/<car>/scan               | Scan           | sensor OR sim             | policy, baseline      |
| racecav/<car>/cmd                | DriveCommand   | policy OR baseline        | actuator OR sim       |
| racecav/<car>/teleop             | DriveCommand   | a joystick/teleop tool    | actuator (priority)   |
| racecav/<car>/safety             | DriveCommand   | safety supervisor (brake) | actuator OR sim (mux) |
| racecav/<car>/drive_ros          | DriveCommand   | ROS /drive bridge ("ros") | actuator OR sim (mux) |
| racecav/<car>/estop              | any payload    | anyone ("clear" to clear) | actuator              |
| racecav/<car>/state              | VehicleState   | sim (or odometry)         | baseline, eval        |
| racecav/<car>/obstacles          | ObstacleStates | sim (ground truth)        | eval, baseline oracle |
| racecav/<car>/vesc               | ServiceStatus-like VESC values | actuator | monitoring     |
| racecav/<car>/<service>/status   | ServiceStatus  | queryable of every service| `racecav state`       |
| racecav/<car>/<service>/alive    | liveliness     | token of every service    | `racecav state`       |
| racecav/<car>/<service>/<query>  | per service    | extra queryables (reset, scenario) |              |
"""

PREFIX = "racecav"

SCAN = "scan"
CMD = "cmd"
TELEOP = "teleop"
SAFETY = "safety"  # brake input of the actuator from the safety supervisor (services/safety)
DRIVE_ROS = "drive_ros"  # DriveCommand from ROS /drive (services/ros2), below teleop in the mux
ESTOP = "estop"
STATE = "state"
OBSTACLES = "obstacles"


def topic(car: str, name: str) -> str:
    """Key of a role topic, e.g. topic("car0", SCAN) == "racecav/car0/scan"."""
    return f"{PREFIX}/{car}/{name}"


def service_key(car: str, service: str, leaf: str) -> str:
    """Key of a service's own resource: status, alive, or an extra queryable."""
    return f"{PREFIX}/{car}/{service}/{leaf}"


def alive_key(car: str, service: str = "*") -> str:
    return service_key(car, service, "alive")


def status_key(car: str, service: str = "*") -> str:
    return service_key(car, service, "status")
