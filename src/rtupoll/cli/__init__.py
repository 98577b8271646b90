"""The ``rtupoll`` command: a lazy click group and the one place errors become exit codes.

Subcommands live in their own modules and are imported only when run, so a
one-shot ``rtupoll read`` does not pay for the simulator or the live table.

The process boundary is handled here too: a signal while Python is still importing,
a closed or full stdout, closed standard descriptors. Each is one line and an exit
code, never a traceback.
"""

from __future__ import annotations

import _signal  # type: ignore[import-not-found]  # the builtin behind signal: already loaded
import codecs
import contextlib
import functools
import io
import os
import sys
from types import FrameType

# errors.Interrupted.exit_code, for the handler below: it is in place before rtupoll's own
# modules are imported, errors.py among them (tests/config/test_hostile_files.py checks the two)
EARLY_EXIT = 130


def _interrupted_early(signum: int, frame: FrameType | None) -> None:
    """SIGINT/SIGTERM before the command runs (click and the command's modules are being
    imported). Nothing has started, so nothing is lost by leaving at once; raising here
    instead would interrupt an import half-way, and importlib then shows its own traceback."""
    with contextlib.suppress(OSError):
        os.write(2, b"rtupoll: interrupted\n")
    os._exit(EARLY_EXIT)


# The console script imports this module first: from here on an early Ctrl-C or SIGTERM
# is one line and exit 130, not a KeyboardInterrupt traceback or a silent kill. Only in
# rtupoll's own process (the console script, ``python -m rtupoll``): another program that
# imports rtupoll (``python -m pytest``) keeps its own Ctrl-C.
_ARGV0 = sys.argv[0] if sys.argv else ""
_CONSOLE = os.path.basename(_ARGV0) == "rtupoll" or \
    _ARGV0.endswith(os.path.join("rtupoll", "__main__.py"))
if _CONSOLE:
    for _sig in (_signal.SIGINT, _signal.SIGTERM):
        _signal.signal(_sig, _interrupted_early)


def _interrupted_late(code: int) -> None:
    """SIGINT/SIGTERM once the command has ended: it changes nothing, so say so and
    leave with the command's own status."""
    def handler(signum: int, frame: FrameType | None) -> None:
        with contextlib.suppress(OSError):
            os.write(2, f"rtupoll: interrupted after the command had ended (exit {code}): "
                        "what it printed is complete\n".encode())
        os._exit(code)

    for sig in (_signal.SIGINT, _signal.SIGTERM):
        _signal.signal(sig, handler)


def _leave(code: int) -> None:
    """The console process's end, once the command is done and its output flushed:
    straight out, without the interpreter's teardown (tens of milliseconds, during
    which Python runs no signal handler: a Ctrl-C there killed the process silently,
    after a write's table, as if the write had been cut short)."""
    _interrupted_late(code)
    for stream in (sys.stdout, sys.stderr):
        with contextlib.suppress(Exception):
            if stream is not None:
                stream.flush()
    logging = sys.modules.get("logging")  # never imported: no handler to flush (and a
    if logging is not None:  # one-shot read does not import it just to end)
        logging.shutdown()
    if hasattr(_signal, "pthread_sigmask"):  # one held by _hold runs its handler now
        _signal.pthread_sigmask(_signal.SIG_UNBLOCK, {_signal.SIGINT, _signal.SIGTERM})
    os._exit(code)

import importlib  # noqa: E402
import signal  # noqa: E402
from collections.abc import Iterator  # noqa: E402
from typing import TYPE_CHECKING, Any, TextIO  # noqa: E402

import click  # noqa: E402

from rtupoll.errors import Interrupted, RtupollError, UsageError, exit_codes  # noqa: E402

if TYPE_CHECKING:
    import asyncio

# command name -> "module:attribute", imported on first use
COMMANDS: dict[str, tuple[str, str]] = {
    "poll": ("rtupoll.cli.poll:poll", "Poll devices and show decoded readings live."),
    "read": ("rtupoll.cli.read:read", "Read fields (or raw registers) from one device once."),
    "write": ("rtupoll.cli.write:write", "Write fields (or raw registers), then read back."),
    "set-address": ("rtupoll.cli.address:set_address", "Give a device a new address, verified."),
    "scan": ("rtupoll.cli.scan:scan", "Find and identify the devices on a bus."),
    "guess": ("rtupoll.cli.guess:guess", "Rank interpretations of an unknown device's registers."),
    "send": ("rtupoll.cli.send:send", "Send one request of any function, decoded and raw."),
    "doctor": ("rtupoll.cli.doctor:doctor", "Check the adapter and a device: findings, fixes."),
    "decode": ("rtupoll.cli.decode:decode", "Decode captured RTU frames."),
    "simulate": ("rtupoll.cli.simulate:simulate", "Serve simulated devices on a pty or TCP."),
    "sniff": ("rtupoll.cli.sniff:sniff", "Listen to a bus another master owns, decoded."),
    "profiles": ("rtupoll.cli.profiles:profiles", "List, show and check device profiles."),
    "web": ("rtupoll.cli.web:web", "Show every gateway on an MQTT broker on one web page."),
}



def exit_codes_text() -> str:
    """The ``--help`` epilog: every exit code, made from the error tree."""
    import textwrap

    lines = ["\b", "Exit codes:"]
    for code, meaning in exit_codes():
        first, *rest = textwrap.wrap(meaning, 74)
        lines += [f"  {code:<3} {first}", *(f"      {more}" for more in rest)]
    return "\n".join(lines) + "\n"


def __getattr__(name: str) -> str:
    """``EXIT_CODES``, the epilog, made when asked for (a command that runs never is)."""
    if name == "EXIT_CODES":
        return exit_codes_text()
    raise AttributeError(f"module {__name__!r} has no attribute {name!r}")


class LazyGroup(click.Group):
    def invoke(self, ctx: click.Context) -> Any:
        """Every command runs through here, so this is the one place errors become exit codes."""
        try:
            return super().invoke(ctx)
        except RtupollError as exc:
            click.echo(f"rtupoll: {exc}", err=True)
            raise click.exceptions.Exit(exc.exit_code) from None
        except KeyboardInterrupt:
            click.echo("rtupoll: interrupted", err=True)
            raise click.exceptions.Exit(Interrupted.exit_code) from None

    def list_commands(self, ctx: click.Context) -> list[str]:
        return sorted(COMMANDS)

    def resolve_command(self, ctx: click.Context, args: list[str]
                        ) -> tuple[str | None, click.Command | None, list[str]]:
        name = args[0] if args else ""
        if name and not name.startswith("-") and name not in COMMANDS:
            from rtupoll.model.names import close_names

            hint = close_names(name, COMMANDS)
            raise click.UsageError(f"no command {name!r}"
                                   + (f" (did you mean {hint[0]!r}?)" if hint else ""), ctx)
        return super().resolve_command(ctx, args)

    def get_command(self, ctx: click.Context, cmd_name: str) -> click.Command | None:
        if cmd_name not in COMMANDS:
            return None
        module, _, attr = COMMANDS[cmd_name][0].partition(":")
        command = getattr(importlib.import_module(module), attr)
        assert isinstance(command, click.Command)
        return command

    def format_epilog(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        self.epilog = exit_codes_text()  # made for the help only
        super().format_epilog(ctx, formatter)

    def format_commands(self, ctx: click.Context, formatter: click.HelpFormatter) -> None:
        # list commands without importing them
        with formatter.section("Commands"):
            formatter.write_dl([(name, COMMANDS[name][1]) for name in self.list_commands(ctx)])


@click.group(cls=LazyGroup,
             context_settings={"help_option_names": ["-h", "--help"]})
@click.version_option(package_name="rtupoll")
def cli() -> None:
    """Modbus RTU devices on RS-485 buses: poll, read, write, readdress, scan.

    Device knowledge comes from YAML profiles (see 'rtupoll profiles list').
    Devices are written PROFILE@ADDRESS, e.g. net-irnet-pro@1.
    """


def main(argv: list[str] | None = None) -> Any:
    """The console script: usage mistakes are one line too, like every other error."""
    args = sys.argv[1:] if argv is None else argv
    if args and args[0] in COMMANDS:  # imported while a signal still just ends the process
        cli.get_command(click.Context(cli), args[0])
    ending = _CONSOLE and argv is None  # rtupoll's own process, not a caller's main([...])
    with contextlib.ExitStack() as process:
        try:  # (a Ctrl-C in the instant _process sets up is "interrupted" too)
            process.enter_context(_process())
            code = cli.main(args=argv, prog_name="rtupoll", standalone_mode=False)
            sys.stdout.flush()  # a full disk shows here, not as "Exception ignored" at exit
            _hold(ending)
        except click.exceptions.NoArgsIsHelpError as exc:  # plain 'rtupoll': the help
            _hold(ending)
            click.echo(exc.ctx.get_help() if exc.ctx else str(exc))
            code = 0
        except click.exceptions.UsageError as exc:
            _hold(ending)
            where = exc.ctx.command_path if exc.ctx else "rtupoll"
            click.echo(f"rtupoll: {exc.format_message()} (see '{where} --help')", err=True)
            code = exc.exit_code
        except click.ClickException as exc:
            _hold(ending)
            exc.show()
            code = exc.exit_code
        except (click.exceptions.Abort, KeyboardInterrupt):
            _hold(ending)
            click.echo("rtupoll: interrupted", err=True)
            code = Interrupted.exit_code
        except BrokenPipeError:  # `rtupoll read ... | head -1`: the reader is done
            _hold(ending)
            code = 0
        except RtupollError as exc:  # an output error outside a command
            _hold(ending)
            click.echo(f"rtupoll: {exc}", err=True)
            code = exc.exit_code
        except Exception as exc:  # Ctrl-C inside an import comes out as importlib's error
            _hold(ending)
            if not _from_interrupt(exc):
                raise
            click.echo("rtupoll: interrupted", err=True)
            code = Interrupted.exit_code
    code = code if isinstance(code, int) else 0
    if ending:
        _leave(code)
    sys.exit(code)


def _hold(ending: bool) -> None:
    """In rtupoll's own process, once the command is over (its outcome known): SIGINT
    and SIGTERM wait (blocked) for ``_leave``'s handler, which says the command had
    ended, instead of a KeyboardInterrupt raised where nothing catches it any more."""
    if ending and hasattr(signal, "pthread_sigmask"):
        signal.pthread_sigmask(signal.SIG_BLOCK, {signal.SIGINT, signal.SIGTERM})


def _from_interrupt(exc: BaseException | None) -> bool:
    """``exc`` was raised while a KeyboardInterrupt was being handled."""
    seen = 0
    while exc is not None and seen < 20:
        if isinstance(exc, KeyboardInterrupt):
            return True
        exc, seen = exc.__context__, seen + 1
    return False


_AWAKE = 0.2  # s: how soon a Ctrl-C is seen where the loop takes no signal handlers
_LOST: list[bool] = []  # a Ctrl-C's KeyboardInterrupt that Python dropped, this command


def _dropped(hook: Any, unraisable: Any) -> None:
    """``sys.unraisablehook`` while a command runs: Python drops what is raised where it
    cannot propagate (a weakref callback or a ``__del__`` that runs at that instant:
    "Exception ignored in ..."); a Ctrl-C's KeyboardInterrupt raised there is remembered."""
    if unraisable.exc_type is not None and issubclass(unraisable.exc_type, KeyboardInterrupt):
        _LOST.append(True)
    hook(unraisable)


def stop_event() -> asyncio.Event:
    """For a command that runs until stopped, in its event loop: an event SIGINT or
    SIGTERM sets (the loop finishes what it writes, then stops; where the loop takes no
    signal handlers, Windows's, a Python handler sets it, so Ctrl-C ends a command there
    as here, with the same exit code); set at once if a Ctrl-C
    came before and Python dropped its KeyboardInterrupt (``_dropped``: the command
    would otherwise run on, as if it had not come)."""
    import asyncio

    stop = asyncio.Event()
    loop = asyncio.get_running_loop()

    def noted(signum: int, frame: FrameType | None) -> None:  # (the loop's thread is ours)
        loop.call_soon_threadsafe(stop.set)

    def awake() -> None:  # a Python handler runs once the loop's select returns
        if not stop.is_set():
            loop.call_later(_AWAKE, awake)

    for sig in (signal.SIGINT, signal.SIGTERM):
        try:
            loop.add_signal_handler(sig, stop.set)
        except NotImplementedError:  # Windows's loops have none: Python's own handler
            with contextlib.suppress(ValueError):  # (put back when the command ends: _process)
                signal.signal(sig, noted)
            if sig == signal.SIGINT:
                awake()  # its select is not interrupted by Ctrl-C: it wakes this often
        except (RuntimeError, ValueError):  # not the main thread
            pass
    if _LOST:
        stop.set()
    return stop


@contextlib.contextmanager
def noted_signals() -> Iterator[list[int]]:
    """For a command that runs until stopped, without an event loop: while the block
    runs, SIGINT and SIGTERM are appended to the list it gets, and nothing else (a
    handler runs between two bytecodes of the main thread, which may hold a lock then:
    ``threading.Event.set`` here once deadlocked inside ``Event.wait``); a Ctrl-C whose
    KeyboardInterrupt Python dropped before is there at once. The handlers are put back
    afterwards."""
    caught: list[int] = []

    def note(signum: int, frame: FrameType | None) -> None:
        caught.append(signum)

    previous = {s: signal.signal(s, note) for s in (signal.SIGINT, signal.SIGTERM)}
    if _LOST:
        caught.append(signal.SIGINT)
    try:
        yield caught
    finally:
        for s, handler in previous.items():
            signal.signal(s, handler)


def _as_sigint(signum: int, frame: FrameType | None) -> None:
    """SIGTERM does what Ctrl-C does at that moment (asyncio's handler cancels the main
    task, so cleanup and reports run; elsewhere a KeyboardInterrupt)."""
    handler = signal.getsignal(signal.SIGINT)
    if callable(handler) and handler is not _as_sigint:
        handler(signal.SIGINT, frame)
        return
    raise KeyboardInterrupt


@contextlib.contextmanager
def _process() -> Iterator[None]:
    """While a command runs: SIGINT and SIGTERM interrupt it (commands that run until
    stopped install their own handlers), stdout errors are one line, and descriptors
    0-2 are open (a port opened on a closed fd 1 would get the report written into it)."""
    for fd, mode in ((0, os.O_RDONLY), (1, os.O_RDONLY), (2, os.O_WRONLY)):
        try:
            os.fstat(fd)
        except OSError:  # closed: hold it with /dev/null (fd 1 read-only, so writes fail)
            held = os.open(os.devnull, mode)
            if held != fd:
                os.dup2(held, fd)
                os.close(held)
    if sys.stdin is None:
        sys.stdin = open(0, encoding="utf-8", closefd=False)  # noqa: SIM115
    if sys.stdout is None:
        sys.stdout = open(1, "w", encoding="utf-8", closefd=False)  # noqa: SIM115
    if sys.stderr is None:
        sys.stderr = open(2, "w", encoding="utf-8", closefd=False)  # noqa: SIM115
    for stream in (sys.stdout, sys.stderr):
        # a code page (Windows's ANSI one, 1252, where output is a pipe or a file) lacks
        # characters of some profiles' texts and of the tables: a '?' for those, not a
        # UnicodeEncodeError's traceback
        if (isinstance(stream, io.TextIOWrapper)
                and codecs.lookup(stream.encoding).name != "utf-8"):
            stream.reconfigure(errors="replace")
    previous = {s: signal.getsignal(s) for s in (signal.SIGINT, signal.SIGTERM)}
    hook = sys.unraisablehook
    _LOST.clear()
    sys.unraisablehook = functools.partial(_dropped, hook)
    # Python's own handler: asyncio.run cancels its task on Ctrl-C only under this one
    signal.signal(signal.SIGINT, signal.default_int_handler)
    signal.signal(signal.SIGTERM, _as_sigint)
    real = sys.stdout
    sys.stdout = _GuardedOutput(real)
    try:
        yield
    finally:
        for sig, handler in previous.items():
            signal.signal(sig, handler)
        sys.unraisablehook = hook
        _LOST.clear()
        sys.stdout = real


class _GuardedOutput:
    """stdout whose write errors are an ``RtupollError`` (disk full, closed) or a plain
    ``BrokenPipeError`` (the reader is done); afterwards fd 1 is /dev/null, so the
    interpreter's flush at exit has nothing to complain about."""

    def __init__(self, stream: TextIO) -> None:
        self._stream = stream

    def write(self, text: str) -> int:
        try:
            return self._stream.write(text)
        except OSError as exc:
            raise self._failed(exc) from None

    def writelines(self, lines: Any) -> None:
        for line in lines:
            self.write(line)

    def flush(self) -> None:
        try:
            self._stream.flush()
        except OSError as exc:
            raise self._failed(exc) from None

    def __getattr__(self, name: str) -> Any:
        return getattr(self._stream, name)

    def _failed(self, exc: OSError) -> Exception:
        try:
            null = os.open(os.devnull, os.O_WRONLY)
            os.dup2(null, self._stream.fileno())
            os.close(null)
        except (OSError, ValueError):
            pass
        if isinstance(exc, BrokenPipeError):
            return exc
        return UsageError(f"cannot write the output: {exc.strerror or exc}")
