"""{{name}}: a subsume robot component, made by `subsume new`.

A starting point that already drives a robot: while something within the
front cone (`cone` radians wide, centred on the heading) is nearer than
`threshold`, it emits `VEL <creep-speed> <turn>` on every tick, turning
toward the side whose nearest obstacle is farther; otherwise it stays
silent, and a lower-priority source drives. Its ports and parameters match
the demo's obstacle avoider, so it can take that one's place in subsume's
config/demo.xml.

Built against the contract subsume:robot@0.2.0 (wit/robot.wit). `ranges`
takes a range scan with its geometry (a simulated robot's serial link sends
one: each ray's angle is `angle_min + i * angle_increment`, and readings
outside `[range_min, range_max]` are no obstacle), or a plain vector of
ranges (a filter's output), whose rays are taken as spread evenly over
`fov` from right to left. `on_input` and `tick` return nothing: a problem
goes to `host.report`, and the component keeps running.

`make bindings` writes the generated `wit_world` package here, for your
editor; componentize-py makes it afresh at every build.
"""

import math

import wit_world
from componentize_py_types import Err
from wit_world.imports import host
from wit_world.imports.types import (
    Description,
    LogLevel,
    Param,
    ParamKind,
    ParamSpec,
    PortSpec,
    Value,
    Value_Command,
    Value_Scan,
    Value_Vector,
    ValueKind,
)

settings = {"threshold": 0.5, "fov": math.pi, "cone": 1.6, "turn-rate": 1.2, "creep-speed": 0.0}
# The latest readings as (angle in radians, counter-clockwise from ahead; metres).
rays: list[tuple[float, float]] = []


def readings(value: Value) -> list[tuple[float, float]] | None:
    """Each ray's (angle, range), from a scan's geometry or spread over fov."""
    if isinstance(value, Value_Scan):
        scan = value.value
        return [
            (scan.angle_min + i * scan.angle_increment, r)
            for i, r in enumerate(scan.ranges)
            if scan.range_min <= r < scan.range_max
        ]
    if isinstance(value, Value_Vector):
        n = len(value.value)
        step = settings["fov"] / (n - 1) if n > 1 else 0.0
        return [(-settings["fov"] / 2 + i * step, r) for i, r in enumerate(value.value)]
    return None


class WitWorld(wit_world.WitWorld):
    def describe(self) -> Description:
        """Declared once: the host reads it before `init` to check the wiring."""

        def number(name: str, default: str, doc: str) -> ParamSpec:
            return ParamSpec(name, ParamKind.NUMBER, default, doc)

        return Description(
            name="{{name}}",
            version="0.1.0",
            summary="Turns away from what is close in front",
            inputs=[PortSpec("ranges", ValueKind.ANY, "a range scan with its geometry, or ranges right to left over fov")],
            outputs=[PortSpec("cmd", ValueKind.COMMAND, "VEL commands while something is close; silent otherwise")],
            params=[
                number("threshold", "0.5", "nearer than this in front (metres) is too close"),
                number("fov", "3.14159", "angle a plain vector of ranges covers, radians (a scan carries its own)"),
                number("cone", "1.6", "width of the watched front cone, radians"),
                number("turn-rate", "1.2", "turn rate while turning away, rad/s"),
                number("creep-speed", "0.0", "forward speed while turning away, m/s"),
            ],
            default_priority=3,
        )

    def init(self, params: list[Param]) -> None:
        # Every declared parameter arrives, already checked against its kind.
        for p in params:
            settings[p.name] = float(p.value)
        if settings["fov"] <= 0.0 or settings["cone"] <= 0.0:
            raise Err("fov and cone must be positive")  # refuses to start
        host.log(LogLevel.INFO, f"ready: turning away from anything nearer than {settings['threshold']} m")

    def on_input(self, port: int, value: Value) -> None:
        global rays
        seen = readings(value)
        if seen is None:
            host.report(f"ranges: expected a scan or a vector, got {type(value).__name__}")
            return
        rays = seen

    def tick(self, now_ns: int) -> None:
        def nearest(side) -> float:
            return min((r for a, r in rays if side(a)), default=math.inf)

        if nearest(lambda a: abs(a) <= settings["cone"] / 2) < settings["threshold"]:
            left, right = nearest(lambda a: a > 0), nearest(lambda a: a < 0)
            turn = settings["turn-rate"] if left >= right else -settings["turn-rate"]
            host.emit(0, Value_Command(f"VEL {settings['creep-speed']:.3f} {turn:.3f}"))
