"""Zenoh key expressions (docs/design.md): every key lives under ``fleet/<fleet-id>/``.

- ``robots/<id>/map``   a robot's trusted segment map (put on change; the agent's queryable answers
  with its latest map so a restarted server can pull it);
- ``robots/<id>/pose``  a robot's pose, often;
- ``robots/<id>/alive`` liveliness token (presence);
- ``robots/<id>/free``  the space a robot's laser saw free, per view (put on change, every 15 s at
  most; queryable like the map);
- ``map/fused``         the fused map (put on change; the server's queryable answers with the latest);
- ``map/free``          the fleet's free space in the global frame (put on change; queryable);
- ``map/paths/<id>``    where the fleet's pose graph puts a robot's keyframes (queryable).
"""

from __future__ import annotations

from shared.messages import ID_PATTERN, WireFormatError, check_id

DEFAULT_FLEET = "default"


class Keys:
    """Key expressions of one fleet."""

    def __init__(self, fleet: str = DEFAULT_FLEET):
        self.fleet = check_id("fleet", fleet)
        self.prefix = f"fleet/{fleet}"

    def robot_map(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_id('robot', robot)}/map"

    def robot_pose(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_id('robot', robot)}/pose"

    def robot_alive(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_id('robot', robot)}/alive"

    def robot_free(self, robot: str) -> str:
        return f"{self.prefix}/robots/{check_id('robot', robot)}/free"

    @property
    def all_free(self) -> str:
        return f"{self.prefix}/robots/*/free"

    @property
    def fused_free(self) -> str:
        return f"{self.prefix}/map/free"

    @property
    def all_maps(self) -> str:
        return f"{self.prefix}/robots/*/map"

    @property
    def all_poses(self) -> str:
        return f"{self.prefix}/robots/*/pose"

    @property
    def all_alive(self) -> str:
        return f"{self.prefix}/robots/*/alive"

    @property
    def fused(self) -> str:
        return f"{self.prefix}/map/fused"

    def robot_path(self, robot: str) -> str:
        return f"{self.prefix}/map/paths/{check_id('robot', robot)}"

    @property
    def all_paths(self) -> str:
        return f"{self.prefix}/map/paths/*"

    def robot_of(self, key: str) -> str:
        """The robot id in a concrete ``.../robots/<id>/...`` key; raises if the key is not one."""
        parts = str(key).split("/")
        head = self.prefix.split("/")
        if len(parts) != len(head) + 3 or parts[: len(head)] != head or parts[len(head)] != "robots":
            raise WireFormatError(f"key: {str(key)[:120]!r} is not a robot key of fleet {self.fleet!r}")
        robot = parts[len(head) + 1]
        if not ID_PATTERN.match(robot):
            raise WireFormatError(f"key: {str(key)[:120]!r} has a bad robot id")
        return robot
