"""A test component for the hostile-component suite (tests/all/hostile.rs).

The obstacle avoider's shape (a `ranges` input, a `cmd` output, priority 3)
that drives (`VEL 0.3 0` on every tick) for `after` ticks and then sleeps
10 s in `tick` with `time.sleep`, as a careless Python author would. The
host must stop it at once: a sleep would hold the control loop. With
`mode` = `raise` it raises an exception instead, whose text must reach the
fault reason.
"""

import time

import wit_world
from wit_world.imports import host
from wit_world.imports.types import (
    Description,
    Param,
    ParamKind,
    ParamSpec,
    PortSpec,
    Value,
    Value_Command,
    ValueKind,
)

after = 10
mode = "sleep"
ticks = 0


class WitWorld(wit_world.WitWorld):
    def describe(self) -> Description:
        return Description(
            name="test-sleeper",
            version="0.1.0",
            summary="Drives, then sleeps 10 s in tick (for the hostile-component tests)",
            inputs=[PortSpec("ranges", ValueKind.VECTOR, "ignored")],
            outputs=[PortSpec("cmd", ValueKind.COMMAND, "VEL 0.3 0 on every tick before the sleep")],
            params=[
                ParamSpec("after", ParamKind.INTEGER, "10", "ticks that drive before the sleep"),
                ParamSpec("mode", ParamKind.TEXT, "sleep", "what it does then: sleep, or raise an exception"),
            ],
            default_priority=3,
        )

    def init(self, params: list[Param]) -> None:
        global after, mode
        for p in params:
            if p.name == "after":
                after = int(p.value.strip())
            if p.name == "mode":
                mode = p.value.strip()

    def on_input(self, port: int, value: Value) -> None:
        pass

    def tick(self, now_ns: int) -> None:
        global ticks
        ticks += 1
        if ticks > after and mode == "raise":
            raise ValueError(f"giving up on purpose at tick {ticks}")
        if ticks > after:
            time.sleep(10)
        host.emit(0, Value_Command("VEL 0.3 0"))
