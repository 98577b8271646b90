"""One exception tree for everything rtupoll reports to a user.

Every error a user can cause or meet carries its own exit code, so the CLI maps
errors to exit codes in exactly one place (``cli.main``) and scripts can tell a
wiring fault from a typo. The codes are documented in the README. Each also carries
its ``status``, the word an MQTT command's result gives for it (docs/mqtt.md).
"""

from __future__ import annotations

from typing import TYPE_CHECKING, ClassVar

if TYPE_CHECKING:
    from rtupoll.rtu.transaction import Evidence


class RtupollError(Exception):
    """Base of every error rtupoll reports as one line, never as a traceback. A class
    that owns an exit code says what it means (``meaning``: ``--help`` shows it);
    ``status`` is its word in an MQTT command's result."""

    exit_code = 1
    status = "error"
    meaning: ClassVar[str]


class UsageError(RtupollError):
    """Bad arguments: a device spec, register spec or option that makes no sense."""

    exit_code = 2
    status = "usage"
    meaning = "bad arguments, profile or configuration; output that cannot be written"


class ProfileError(RtupollError):
    """A profile or site configuration that does not validate.

    Rendered as ``file:line: field.path: message`` so an editor can jump there.
    """

    exit_code = 2

    def __init__(self, message: str, *, file: str = "", line: int = 0, path: str = "") -> None:
        self.file, self.line, self.path, self.message = file, line, path, message
        where = f"{file}:{line}: " if file and line else (f"{file}: " if file else "")
        super().__init__(f"{where}{path + ': ' if path else ''}{message}")


class MissingLibrary(UsageError):
    """A feature whose optional library is not installed. The message is the one command
    that installs it into the very Python that runs rtupoll (a venv, pipx's, the
    system's), with the version range pyproject.toml gives its extra: it works as printed,
    where ``pip install 'rtupoll[EXTRA]'`` would look for rtupoll on an index."""

    def __init__(self, feature: str, extra: str) -> None:
        self.extra = extra
        names, command = install_command(extra)
        super().__init__(f"{feature} needs {names}: {command}")


def install_command(extra: str) -> tuple[str, str]:
    """The libraries of an extra (``aiomqtt``) and the command that installs them."""
    import os
    import shlex
    import sys
    from importlib import metadata

    try:
        requires = metadata.requires("rtupoll") or []
    except metadata.PackageNotFoundError:  # run from a source tree that was never installed
        requires = []

    def of(extra: str) -> list[str]:  # ``rtupoll[a,b]`` (edge) stands for a's and b's
        out = []
        for r in requires:
            spec, _, marker = r.partition(";")
            if marker.replace("'", '"').strip() != f'extra == "{extra}"':
                continue
            if spec.startswith("rtupoll["):
                out += [w for e in spec.strip()[8:-1].split(",") for w in of(e.strip())]
            else:
                out.append(spec.strip())
        return out

    wanted = of(extra)
    if not wanted:
        return f"the {extra!r} extra", f"pip install -e '.[{extra}]' (in rtupoll's clone)"
    names = ", ".join(w.split("<")[0].split(">")[0].split("=")[0].strip() for w in wanted)
    words = [sys.executable, "-m", "pip", "install", *wanted]
    if os.name == "nt":  # cmd and PowerShell both take double quotes
        return names, " ".join(f'"{w}"' if set(w) & set(' <>&|') else w for w in words)
    return names, shlex.join(words)


class FaultSpecError(UsageError):
    """A simulator fault spec that does not parse; the message says what was expected."""


class ConfigError(ProfileError):
    """A site configuration (buses and devices) that does not validate."""


class PortError(RtupollError):
    """The port cannot be opened (missing, busy, no permission, unreachable gateway), or
    went away under a command that ends with it (``sniff``: the adapter unplugged)."""

    exit_code = 3
    status = "port"
    meaning = "port cannot be opened (missing, busy, no permission) or went away"


class BusError(RtupollError):
    """A transaction on the bus failed. ``evidence``: what it told of the unit's timing
    (an exception reply's reply time, late replies, attempts), set by the bus."""

    exit_code = 4
    evidence: Evidence | None = None


class DeviceTimeout(BusError):
    """No (valid) reply within the device's timeout."""

    exit_code = 4
    status = "timeout"
    meaning = "no response from the device"


class FrameError(BusError):
    """A reply arrived but was unusable: CRC error, garbage, truncated or malformed."""

    exit_code = 7
    status = "garbled"
    meaning = "garbled reply (CRC error, truncated or malformed frame, an echoing adapter)"


class DeviceException(BusError):
    """The device answered with a Modbus exception response."""

    exit_code = 5
    status = "exception"
    meaning = ("the device answered with a Modbus exception (read: the fields that answered "
               "are printed, the refused one with its exception)")

    def __init__(self, code: int, *, unit: int | None = None, function: int | None = None) -> None:
        from rtupoll.rtu import exception_name

        self.code, self.unit, self.function = code, unit, function
        who = f"device {unit}" if unit is not None else "device"
        fc = f" to function 0x{function:02X}" if function is not None else ""
        super().__init__(f"{who} answered{fc} with exception {code:02d} {exception_name(code)}")


class VerificationError(RtupollError):
    """A write was sent but reading back does not show the intended result."""

    exit_code = 6
    status = "verification"
    meaning = "verification failed (a write did not take effect)"


class PlanFailed(RtupollError):
    """A row of an address plan failed: its message, and the exit code of its cause."""

    def __init__(self, row: int, cause: RtupollError) -> None:
        super().__init__(f"row {row}: {cause}")
        self.exit_code = cause.exit_code


class RefusedError(RtupollError):
    """A request refused before anything was sent, because it would be unsafe or wrong.

    For example a read-only field, a value out of range, a reserved or taken address.
    """

    exit_code = 8
    status = "refused"
    meaning = ("refused before sending (read-only field, a value its type cannot hold, "
               "address taken)")


class Interrupted(RtupollError):
    """Ctrl-C or SIGTERM: what was under way stops cleanly (``rtupoll: interrupted``)."""

    exit_code = 130
    meaning = ("interrupted (Ctrl-C or SIGTERM) before it finished; poll, simulate, sniff "
               "and web, once running, stop on them with 0")


class ScanIncomplete(RtupollError):
    """``poll --once``: one or more devices failed; each is named on stderr."""

    exit_code = 9
    meaning = "poll --once: one or more devices failed"


class BrokerError(RtupollError):
    """``poll --mqtt``: the MQTT broker cannot be reached or refused us at start-up (unknown
    host, connection refused, wrong user or password, TLS handshake refused)."""

    exit_code = 10
    meaning = "poll --mqtt, web: the broker is unreachable or refused at start-up"


class EncodeError(RefusedError):
    """A value that cannot be represented in a field's type: refused before sending."""


class ClientError(RtupollError):
    """Something a Modbus TCP client sent that the gateway refuses (a malformed frame, a
    request it will not pass on): answered or logged, it never ends rtupoll."""


def exit_codes() -> list[tuple[int, str]]:
    """Every exit code and what it means, from the classes that own one (``meaning``),
    in order: the ``--help`` text and the docs are made from this."""
    found: dict[int, str] = {0: "success"}
    todo: list[type[RtupollError]] = [RtupollError]
    while todo:
        cls = todo.pop()
        todo += cls.__subclasses__()
        if "meaning" in cls.__dict__:
            found.setdefault(cls.exit_code, cls.meaning)
    return sorted(found.items())
