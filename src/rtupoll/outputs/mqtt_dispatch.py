"""Commands from the broker, dispatched: ``BASE/DEVICE/set`` and ``.../get`` to their
device's bus, one result back on ``.../result``.

What a command may do and how it runs on the bus is ``mqtt_commands``; this room finds
the device, runs each command as a task of its own (the broker's reader never waits on
a bus), and says what happened.
"""

from __future__ import annotations

import asyncio
import logging
from typing import TYPE_CHECKING, Any

from rtupoll.errors import RtupollError, UsageError
from rtupoll.outputs import mqtt_commands as cmd
from rtupoll.ui.records import to_json

if TYPE_CHECKING:
    from rtupoll.config.mqtt_settings import MqttSettings
    from rtupoll.jobs.scheduler import BusPoller, DevicePoller, Scheduler
    from rtupoll.outputs.mqtt_connection import Say
    from rtupoll.outputs.mqtt_outbox import Outbox
    from rtupoll.outputs.mqtt_state import StatePublisher

__all__ = ["Commands"]


class Commands:
    """The commands running now, and the devices they may name (topic level -> name)."""

    def __init__(self, settings: MqttSettings, publisher: StatePublisher, outbox: Outbox,
                 say: Say) -> None:
        self.settings = settings
        self.publisher = publisher  # a set or a full get forces the next state out
        self.outbox = outbox
        self.say = say
        self.scheduler: Scheduler | None = None
        self.devices: dict[str, str] = {}  # topic level -> device name
        self._running: set[asyncio.Task[None]] = set()
        self._retained_said = False  # a retained command was ignored, and the log said so

    def take(self, topic: str, payload: bytes, *, retain: bool) -> None:
        """A message under the base topic: a command of a device polled now runs."""
        t, _, verb = topic[len(self.settings.base) + 1:].rpartition("/")
        name = self.devices.get(t)
        if name is None or verb not in ("set", "get"):
            return
        if retain:  # left on the broker, maybe long ago: not a command now
            self._ignored_retained(topic)
            return
        task = asyncio.create_task(self._command(verb, name, t, payload))
        self._running.add(task)
        task.add_done_callback(self._running.discard)

    async def stop(self) -> None:
        for task in list(self._running):
            task.cancel()
        await asyncio.gather(*self._running, return_exceptions=True)

    def _ignored_retained(self, topic: str) -> None:
        if self._retained_said:
            return
        self._retained_said = True
        self.say(logging.WARNING, "mqtt: ignoring the retained command on %s (and any "
                 "other): commands must come from now, not from the broker's memory; clear "
                 "it with: mosquitto_pub -r -n -t '%s'", topic, topic)

    def _find(self, name: str) -> tuple[BusPoller, DevicePoller] | None:
        if self.scheduler is None:
            return None
        for bp in self.scheduler.buses:
            for d in bp.devices:
                if d.config.name == name:
                    return bp, d
        return None

    async def _command(self, verb: str, name: str, t: str, payload: bytes) -> None:
        """``BASE/DEVICE/set`` or ``.../get``: run it, publish its one result on
        ``.../result``, whatever the payload holds."""
        done: dict[str, Any] = {}  # what a set wrote and read back (a get read) before a failure
        try:
            found = self._find(name)
            if found is None:
                raise UsageError(f"{name} is not polled now (the site file was reloaded)")
            bp, dev = found
            values = await (self._set(bp, dev, t, payload, done) if verb == "set" else
                            self._get(bp, dev, t, payload, done))
            if values is None:  # a get of everything: the next state answers it
                return
            result = cmd.ok(values)
        except RtupollError as exc:
            result = cmd.failed(exc, done)
        except Exception as exc:  # a bug: still one result, and one line, no traceback
            result = cmd.failed(RtupollError(f"{verb} failed: {type(exc).__name__}: {exc}"),
                                done)
            self.say(logging.ERROR, "mqtt: %s: %s: %s", name, verb, result["error"],
                     device=name)
        if verb == "set":
            self.say(logging.INFO, "mqtt: %s: set %s: %s", name,
                     payload[:200].decode("utf-8", "replace"), result.get("error") or "ok",
                     device=name)
        self.outbox.put(f"{self.settings.base}/{t}/{verb}/result", to_json(result),
                        retain=False, qos=self.settings.qos)

    async def _set(self, bp: BusPoller, dev: DevicePoller, t: str, payload: bytes,
                   done: dict[str, Any]) -> dict[str, Any]:
        cfg = dev.config
        ops = cmd.plan_set(cfg, payload, writes_on=self.settings.allow_writes,
                           allow=self.settings.options(cfg.name).allow)
        await bp.submit(lambda transport: cmd.apply_set(transport, cfg, ops, done))
        self.publisher.forced.add(t)
        bp.poll_now(dev)
        return done

    async def _get(self, bp: BusPoller, dev: DevicePoller, t: str, payload: bytes,
                   done: dict[str, Any]) -> dict[str, Any] | None:
        """The fields asked for, read now; None for all of them (the next state)."""
        cfg = dev.config
        fields = cmd.plan_get(cfg, payload)
        if fields is None:
            self.publisher.forced.add(t)
            bp.poll_now(dev)
            return None
        return await bp.submit(lambda transport: cmd.apply_get(transport, dev, fields, done))
