"""Obstacle avoider (subsumption layer, default priority 3), in Python.

The same component as guest-components/rust/avoider: the same ports,
parameters, description and commands (tests/all/languages.rs checks it), built
like it against the contract subsume:robot@0.2.0: `on_input` and `tick`
return nothing, and a problem goes to `host.report`.
Reads a range scan whose rays are spread evenly from -fov/2 (right) to
+fov/2 (left) of the heading. While an obstacle inside the front cone is
nearer than `threshold`, it emits `VEL <creep> <turn>` on every tick,
turning toward the freer side. Otherwise it stays silent: silence tells the
arbiter this behaviour is not active, so a lower layer drives.
"""

from dataclasses import dataclass, field

import wit_world
from componentize_py_types import Err
from wit_world.imports import host
from wit_world.imports.types import (
    Description,
    Param,
    ParamKind,
    ParamSpec,
    PortSpec,
    Value,
    Value_Command,
    Value_Vector,
    ValueKind,
)


@dataclass
class Avoider:
    threshold: float
    fov: float
    cone: float
    turn_rate: float
    creep_speed: float
    ranges: list[float] = field(default_factory=list)


# The one instance, made by `init`.
state: Avoider | None = None


def number(params: list[Param], name: str) -> float:
    """Parameter `name` as a number; the host has already checked its kind."""
    for p in params:
        if p.name == name:
            try:
                return float(p.value.strip())
            except ValueError:
                raise Err(f"parameter '{name}': '{p.value}' is not a number")
    raise Err(f"missing parameter '{name}'")


class WitWorld(wit_world.WitWorld):
    def describe(self) -> Description:
        def number_param(name: str, default: str, doc: str) -> ParamSpec:
            return ParamSpec(name, ParamKind.NUMBER, default, doc)

        return Description(
            name="avoider",
            version="0.1.0",
            summary="Turns away from obstacles nearer than a threshold",
            inputs=[
                PortSpec("ranges", ValueKind.VECTOR, "ranges in metres, rays from -fov/2 (right) to +fov/2 (left)")
            ],
            outputs=[PortSpec("cmd", ValueKind.COMMAND, "VEL commands while an obstacle is near; silent otherwise")],
            params=[
                number_param("threshold", "0.5", "an obstacle nearer than this (metres) triggers avoidance"),
                number_param("fov", "3.14159", "angle covered by the scan, radians"),
                number_param("cone", "1.6", "width of the front cone that is watched, radians"),
                number_param("turn-rate", "1.2", "turn rate while avoiding, rad/s"),
                number_param("creep-speed", "0.0", "forward speed while avoiding, m/s"),
            ],
            default_priority=3,
        )

    def init(self, params: list[Param]) -> None:
        global state
        avoider = Avoider(
            threshold=number(params, "threshold"),
            fov=number(params, "fov"),
            cone=number(params, "cone"),
            turn_rate=number(params, "turn-rate"),
            creep_speed=number(params, "creep-speed"),
        )
        if avoider.threshold <= 0.0 or avoider.fov <= 0.0 or avoider.cone <= 0.0:
            raise Err("threshold, fov and cone must be positive")
        state = avoider

    def on_input(self, port: int, value: Value) -> None:
        if state is None:
            host.report("on-input called before init")
        elif not isinstance(value, Value_Vector):
            host.report("ranges: expected a vector")
        else:
            state.ranges = value.value

    def tick(self, now_ns: int) -> None:
        if state is None:
            host.report("tick called before init")
            return
        n = len(state.ranges)
        if n == 0:
            return
        step = state.fov / (n - 1) if n > 1 else 0.0
        near, left, right = False, 0.0, 0.0
        for i, r in enumerate(state.ranges):
            angle = -state.fov / 2.0 + step * i
            if abs(angle) <= state.cone / 2.0 and r < state.threshold:
                near = True
            if angle > 0.0:
                left += r
            elif angle < 0.0:
                right += r
        if near:
            turn = state.turn_rate if left >= right else -state.turn_rate
            host.emit(0, Value_Command(f"VEL {state.creep_speed:.3f} {turn:.3f}"))
