"""{{name}}: a subsume robot component, made by `subsume new`.

A starting point that already drives a robot: while something in the middle
third of the range scan is nearer than `threshold`, it emits
`VEL <creep-speed> <turn>` on every tick, turning toward the side with more
room; otherwise it stays silent, and a lower-priority source drives. Its ports
and parameters match the demo's obstacle avoider, so it can take that one's
place in subsume's config/demo.xml.

`make bindings` writes the generated `wit_world` package here, for your
editor; componentize-py makes it afresh at every build.
"""

import wit_world
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
    Value_Vector,
    ValueKind,
)

settings = {"threshold": 0.5, "turn-rate": 1.2, "creep-speed": 0.0}
ranges: list[float] = []


class WitWorld(wit_world.WitWorld):
    def describe(self) -> Description:
        """Declared once: the host reads it before `init` to check the wiring."""
        return Description(
            name="{{name}}",
            version="0.1.0",
            summary="Turns away from what is close in front",
            inputs=[PortSpec("ranges", ValueKind.VECTOR, "ranges in metres, rays from right to left")],
            outputs=[PortSpec("cmd", ValueKind.COMMAND, "VEL commands while something is close; silent otherwise")],
            params=[
                ParamSpec("threshold", ParamKind.NUMBER, "0.5", "nearer than this in front (metres) is too close"),
                ParamSpec("turn-rate", ParamKind.NUMBER, "1.2", "turn rate while turning away, rad/s"),
                ParamSpec("creep-speed", ParamKind.NUMBER, "0.0", "forward speed while turning away, m/s"),
            ],
            default_priority=3,
        )

    def init(self, params: list[Param]) -> None:
        # Every declared parameter arrives, already checked against its kind.
        # To refuse to start: raise componentize_py_types.Err("why").
        for p in params:
            settings[p.name] = float(p.value)
        host.log(LogLevel.INFO, f"ready: turning away from anything nearer than {settings['threshold']} m")

    def on_input(self, port: int, value: Value) -> None:
        global ranges
        if isinstance(value, Value_Vector):
            ranges = value.value

    def tick(self, now_ns: int) -> None:
        third = len(ranges) // 3
        right, front, left = ranges[:third], ranges[third : len(ranges) - third], ranges[len(ranges) - third :]
        if min(front, default=float("inf")) < settings["threshold"]:
            room_left, room_right = min(left, default=float("inf")), min(right, default=float("inf"))
            turn = settings["turn-rate"] if room_left >= room_right else -settings["turn-rate"]
            host.emit(0, Value_Command(f"VEL {settings['creep-speed']:.3f} {turn:.3f}"))
