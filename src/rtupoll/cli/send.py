"""``rtupoll send``: one request of any function through the disciplined line, its reply
decoded and shown raw.

For what ``read`` and ``write`` do not cover: read device identification (FC 43/14),
report server id (FC 17), diagnostics (FC 8), or a frame a vendor documents. The
request is sent as every other (the silence kept, a late reply never taken for its
answer, retries as given); what it does is judged by the function-effect table
(``rtu.effects``), so anything that is not a plain read needs ``--yes``, as writes do.
"""

from __future__ import annotations

import json
import sys
from typing import TYPE_CHECKING, Any

import click

from rtupoll.cli.options import format_option, port_options
from rtupoll.cli.params import Seconds
from rtupoll.cli.target import confirm, port_settings, run_on_bus
from rtupoll.errors import DeviceException, FrameError, UsageError
from rtupoll.numbers import parse_unit
from rtupoll.rtu import exception_name, with_crc
from rtupoll.rtu import identification as ident
from rtupoll.rtu.effects import Effect, effect
from rtupoll.rtu.functions import FUNCTION_NAMES

if TYPE_CHECKING:
    from rtupoll.io.interface import BusLike

MAX_PARTS = 16  # read device identification requests for one answer ("more follows")
DIAGNOSTIC_NAMES = {
    0x00: "return query data", 0x01: "restart communications option",
    0x02: "return diagnostic register", 0x03: "change ASCII input delimiter",
    0x04: "force listen only mode", 0x0A: "clear counters and diagnostic register",
    0x0B: "return bus message count", 0x0C: "return bus communication error count",
    0x0D: "return bus exception error count", 0x0E: "return server message count",
    0x0F: "return server no response count", 0x10: "return server NAK count",
    0x11: "return server busy count", 0x12: "return bus character overrun count",
    0x14: "clear overrun counter and flag",
}

EPILOG = """\b
Examples:
  rtupoll send -p /dev/ttyUSB0 read-device-id 1
  rtupoll send -p /dev/ttyUSB0 read-device-id 1 regular
  rtupoll send -p /dev/ttyUSB0 report-server-id 1
  rtupoll send -p /dev/ttyUSB0 diagnostics 1 0 A537     (return query data: an echo)
  rtupoll send -p /dev/ttyUSB0 3 04 00 06 00 02         (a PDU in hex: FC 4, 2 registers)
"""


@click.command(epilog=EPILOG)
@click.argument("request", nargs=-1, required=True, metavar="REQUEST...")
@port_options
@click.option("--timeout", type=Seconds(0.01, 30), default=0.5, show_default=True,
              metavar="SECONDS", help="Response timeout per attempt.")
@click.option("--retries", type=click.IntRange(0, 10), default=1, show_default=True,
              help="Retries when there is no (valid) reply.")
@click.option("--yes", "-y", is_flag=True,
              help="Send a request that is not a plain read (writes, state-changing "
                   "diagnostics, unknown functions) without asking.")
@format_option("text", "json")
def send(request: tuple[str, ...], port: str | None, baudrate: int | None, parity: str | None,
         stopbits: str | None, timeout: float, retries: int, yes: bool, fmt: str) -> None:
    """Send one request and show its reply, decoded and raw.

    \b
    REQUEST is one of
      read-device-id UNIT [basic|regular|extended|OBJECT]   FC 43/14, every part
      report-server-id UNIT                                  FC 17
      diagnostics UNIT SUB [DATA]                            FC 8 (SUB, DATA in hex)
      UNIT HEX...                                            any PDU: function, data

    Exit 5 when the device answers with an exception (named), 4 without a reply,
    7 for a reply that does not parse.
    """
    unit, pdu, what = parse_request(request)
    does = effect(pdu)
    if unit == 0 and does is not Effect.WRITE:
        raise UsageError("unit 0 is a broadcast: no device replies, so only writes may go "
                         "there")
    if does is not Effect.READ:
        confirm(f"{what} is {'a ' if does is not Effect.UNKNOWN else ''}"
                f"{does.value if does is not Effect.UNKNOWN else 'of unknown effect'}: "
                f"send it to unit {unit}?", yes)
    settings = port_settings(None, port, baudrate, parity, stopbits)

    async def job(bus: BusLike) -> list[bytes]:
        replies = [await bus.transact(unit, pdu, timeout=timeout, retries=retries)]
        while pdu[0] == 43 and _more(replies[-1]) and len(replies) < MAX_PARTS:
            nxt = ident.parse_device_id(replies[-1]).next_object
            replies.append(await bus.transact(unit, bytes((*pdu[:3], nxt)), timeout=timeout,
                                              retries=retries))
        return replies

    replies = run_on_bus(settings, job, blocking=True)
    _show(unit, pdu, what, replies, fmt)


def parse_request(words: tuple[str, ...]) -> tuple[int, bytes, str]:
    """REQUEST... -> (unit, request PDU, what it is in words)."""
    name, *rest = words
    if name in ("read-device-id", "report-server-id", "diagnostics"):
        if not rest:
            raise UsageError(f"{name} needs UNIT (e.g. {name} 1)")
        unit = _unit(rest[0])
        args = rest[1:]
        if name == "report-server-id":
            if args:
                raise UsageError("report-server-id takes UNIT only")
            return unit, b"\x11", "report server id"
        if name == "read-device-id":
            return (unit, *_device_id(args))
        if not args:
            raise UsageError("diagnostics needs SUB (hex, e.g. 0 for return query data)")
        sub = _hex_int(args[0], 0xFFFF, "SUB")
        data = _hex(args[1:]) if len(args) > 1 else b"\x00\x00"
        label = DIAGNOSTIC_NAMES.get(sub, f"sub-function 0x{sub:04X}")
        return unit, b"\x08" + sub.to_bytes(2, "big") + data, f"diagnostics: {label}"
    unit = _unit(name)
    pdu = _hex(tuple(rest))
    if not pdu:
        raise UsageError("give the request PDU in hex after UNIT (e.g. 3 04 00 06 00 02), "
                         "or read-device-id, report-server-id, diagnostics")
    return unit, pdu, FUNCTION_NAMES.get(pdu[0], f"function 0x{pdu[0]:02X}")


def _device_id(args: list[str]) -> tuple[bytes, str]:
    if len(args) > 1:
        raise UsageError("read-device-id takes UNIT and one of basic, regular, extended or "
                         "an object id")
    which = args[0].lower() if args else "basic"
    if which in ("basic", "regular", "extended"):
        return ident.device_id_request(ident.CODES[which]), f"read device identification " \
            f"({which})"
    obj = _hex_int(which, 0xFF, "OBJECT") if not which.isdigit() else int(which)
    if obj > 0xFF:
        raise UsageError(f"object {obj} is outside 0..255")
    return ident.device_id_request(4, obj), f"read device identification " \
        f"(object 0x{obj:02X} {ident.object_name(obj)})"


def _unit(text: str) -> int:
    try:
        return parse_unit(text)
    except ValueError as exc:
        raise UsageError(str(exc)) from None


def _hex(words: tuple[str, ...] | list[str]) -> bytes:
    text = "".join(words).replace("0x", "").replace(",", "").replace(":", "")
    try:
        return bytes.fromhex(text)
    except ValueError:
        raise UsageError(f"{' '.join(words)!r} is not bytes in hex (e.g. 04 00 06 00 02)") \
            from None


def _hex_int(text: str, top: int, what: str) -> int:
    try:
        value = int(text.lower().removeprefix("0x"), 16)
    except ValueError:
        raise UsageError(f"{what} {text!r} is not a number in hex") from None
    if not 0 <= value <= top:
        raise UsageError(f"{what} {text!r} is outside 0..0x{top:X}")
    return value


def _more(reply: bytes) -> bool:
    return len(reply) >= 7 and reply[:2] == b"\x2b\x0e" and reply[4] == 0xFF


def _show(unit: int, pdu: bytes, what: str, replies: list[bytes], fmt: str) -> None:
    last = replies[-1]
    if last and last[0] & 0x80:
        rec: dict[str, Any] = {"exception": {"code": last[1], "name": exception_name(last[1])}}
    else:
        try:
            rec = _decoded(pdu, replies)
        except ValueError as exc:
            _echo(unit, pdu, what, replies, fmt, {"error": str(exc)})
            raise FrameError(f"device {unit}: the reply does not parse: {exc}") from None
    _echo(unit, pdu, what, replies, fmt, rec)
    if "exception" in rec:
        raise DeviceException(last[1], unit=unit, function=pdu[0])


def _decoded(pdu: bytes, replies: list[bytes]) -> dict[str, Any]:
    fc = pdu[0]
    if fc == 43 and pdu[1:2] == b"\x0e":
        parts = [ident.parse_device_id(r) for r in replies]
        objects = {ident.object_name(o): v.decode("latin-1") for p in parts
                   for o, v in p.objects}
        return {"objects": objects,
                "conformity": ident.CONFORMITY.get(parts[0].conformity,
                                                   f"0x{parts[0].conformity:02X}"),
                "complete": not parts[-1].more}
    if fc == 17:
        sid = ident.parse_server_id(replies[0])
        return {"server_id": sid.server_id.hex(" ").upper(),
                "run_indicator": None if sid.running is None else
                ("ON" if sid.running else "OFF"),
                "additional": sid.additional.hex(" ").upper(),
                "text": sid.data.decode("latin-1") if sid.data.isascii()
                and sid.data.decode("latin-1").isprintable() else None}
    if fc == 8:
        reply = replies[0]
        return {"sub_function": int.from_bytes(reply[1:3], "big"),
                "data": reply[3:].hex(" ").upper(), "echo": reply == pdu}
    return {}


def _echo(unit: int, pdu: bytes, what: str, replies: list[bytes], fmt: str,
          rec: dict[str, Any]) -> None:
    frames = [with_crc(bytes((unit,)) + pdu)]
    if fmt == "json":
        out = {"unit": unit, "function": pdu[0], "request": pdu.hex(" ").upper(),
               "what": what, "replies": [r.hex(" ").upper() for r in replies], **rec}
        click.echo(json.dumps(out, ensure_ascii=False))
        return
    click.echo(f"request  {frames[0].hex(' ').upper()}   {what}")
    for r in replies:  # 16 bytes a line, as a hex view shows them
        frame = with_crc(bytes((unit,)) + r).hex(" ").upper()
        lines = [frame[k : k + 48].rstrip() for k in range(0, len(frame), 48)]
        click.echo("reply    " + "\n         ".join(lines))
    if "exception" in rec:
        e = rec["exception"]
        click.echo(f"  exception {e['code']:02d} {e['name']}")
    for name, value in rec.get("objects", {}).items():
        click.echo(f"  {name:<20} {value}")
    if "conformity" in rec:
        click.echo(f"  {'conformity':<20} {rec['conformity']}"
                   + ("" if rec["complete"] else f" (stopped after {MAX_PARTS} parts)"))
    if "server_id" in rec:
        click.echo(f"  {'server id':<20} {rec['server_id']}")
        where = rec["run_indicator"] or "not where the standard puts it (a longer id?)"
        click.echo(f"  {'run indicator':<20} {where}")
        if rec["additional"]:
            click.echo(f"  {'additional data':<20} {rec['additional']}")
        if rec["text"]:
            click.echo(f"  {'as text':<20} {rec['text']!r}")
    if "sub_function" in rec:
        click.echo(f"  {'data':<20} {rec['data'] or '(none)'}"
                   + ("  (the request's, echoed)" if rec["echo"] else ""))
    sys.stdout.flush()
