"""The command-line guard every console script runs under.

Exit codes, the same for every command (README, "Exit codes"):

- 0: done;
- 1: the command ran to its end but some of its work failed (a session of ``reprocess`` that failed or
  is ``partial``, a camera left out), as it printed;
- 2: bad input or a project error: one message on stderr that says what is wrong and what to do, no
  traceback (argparse's usage errors also exit 2);
- 130: interrupted (Ctrl-C); what was finished is kept. The first Ctrl-C prints "stopping…" at once and
  the command ends within ``STOP_GRACE_S`` (work still running then is dropped: every output is written
  atomically, so nothing half-written is left as a result); a second Ctrl-C ends it at once.

An unexpected exception (a bug) still ends with its traceback, so that it can be reported; set
``ROOMCAP_DEBUG=1`` to see the traceback of the errors above as well.
"""

from __future__ import annotations

import argparse
import errno
import logging
import os
import re
import signal
import sys
import threading
import time
from collections.abc import Callable, Sequence
from pathlib import Path
from typing import Any

from roomcap.core.errors import InputError, RoomcapError
from roomcap.core.redact import redact, redact_log_records

EXIT_OK, EXIT_FAILED, EXIT_INPUT, EXIT_INTERRUPTED = 0, 1, 2, 130
STOP_GRACE_S = 1.5  # after the first Ctrl-C, how long a command may take to stop before it is ended


def _say(text: str) -> None:
    """Write to stderr from a signal handler or a watchdog thread (no locks: os.write)."""
    try:
        os.write(2, text.encode())
    except OSError:
        pass


def _stop_on_sigint(prog: str, hits: list[int]) -> Any:
    """Install the Ctrl-C handler of a command; returns the previous handler (None off the main thread).
    ``hits[0]`` counts the SIGINTs received.

    The first SIGINT says "stopping…" at once and raises KeyboardInterrupt in the main thread, so the
    command unwinds and keeps what it finished; a watchdog ends the process with 130 if it has not ended
    within ``STOP_GRACE_S`` (a thread pool finishing its queue, a native call that does not return, worker
    processes). A second SIGINT ends it at once.
    """
    if threading.current_thread() is not threading.main_thread():
        return None

    def deadline() -> None:
        time.sleep(STOP_GRACE_S)
        _say(f"{prog}: stopped; what was finished is kept (run the command again to go on).\n")
        os._exit(EXIT_INTERRUPTED)

    def handler(signum: int, frame: Any) -> None:
        hits[0] += 1
        if hits[0] > 1:
            _say(f"{prog}: stopped.\n")
            os._exit(EXIT_INTERRUPTED)
        _say(f"{prog}: stopping… (Ctrl-C again to quit at once)\n")
        threading.Thread(target=deadline, name="stop-deadline", daemon=True).start()
        raise KeyboardInterrupt

    return signal.signal(signal.SIGINT, handler)


def interrupted(e: BaseException) -> bool:
    """Whether ``e`` stands for a Ctrl-C: a KeyboardInterrupt itself or in its causes. The SIGINT handler's
    KeyboardInterrupt raised while native code runs (a numba kernel's dispatch) can come back as
    ``SystemError: ... returned a result with an exception set``, its cause the KeyboardInterrupt.

    >>> try:
    ...     raise SystemError("returned a result with an exception set") from KeyboardInterrupt()
    ... except SystemError as err:
    ...     interrupted(err), interrupted(ValueError())
    (True, False)
    """
    seen: set[int] = set()
    cur: BaseException | None = e
    while cur is not None and id(cur) not in seen:
        if isinstance(cur, KeyboardInterrupt):
            return True
        seen.add(id(cur))
        cur = cur.__cause__ or cur.__context__
    return False


def describe_os_error(e: OSError) -> str:
    """An OSError as a sentence: which file, what went wrong, what to do.

    >>> describe_os_error(FileNotFoundError(errno.ENOENT, "No such file or directory", "rig.toml"))
    'No such file or directory: rig.toml (check the path)'
    """
    where = f" {e.filename}" if e.filename else ""
    what = e.strerror or str(e)
    hint = {
        errno.ENOENT: "check the path",
        errno.EACCES: "check the permissions, or choose another folder",
        errno.EPERM: "check the permissions, or choose another folder",
        errno.EROFS: "the file system is read-only: choose another folder",
        errno.ENOSPC: "the disk is full: free space or choose another folder",
        errno.EISDIR: "a folder is there: give a file name",
        errno.ENOTDIR: "a file is there where a folder is needed: choose another path",
        errno.EEXIST: "something is already there: remove it or choose another path",
    }.get(e.errno or -1)
    return f"{what}:{where}" + (f" ({hint})" if hint else "")


_HOME = re.compile(r"^~[A-Za-z0-9._-]*(?=/|$)")


def expand_user_args(argv: Sequence[str]) -> list[str]:
    """``~`` and ``~user`` at the start of an argument, or of an option's value after ``=``, expanded to the
    home folder as a shell does (a shell leaves ``--out=~/x`` and quoted ``'~/x'`` alone), so every path
    option means the home folder and never a folder named ``~``.

    >>> home = os.path.expanduser("~")
    >>> expand_user_args(["--out=~/x", "~/y", "a~b", "--set", "k=~/z"]) == [
    ...     f"--out={home}/x", f"{home}/y", "a~b", "--set", "k=~/z"]
    True
    """
    out = []
    for a in argv:
        flag, eq, value = a.partition("=") if a.startswith("--") else ("", "", a)
        if _HOME.match(value):
            value = os.path.expanduser(value)
        out.append(f"{flag}{eq}{value}" if eq else value if not flag else a)
    return out


def guarded(prog: str, main: Callable[[Sequence[str] | None], int | None]) -> Callable[..., int]:
    """Wrap ``main(argv) -> exit code`` so the project's errors end in one line and a documented code."""

    def run(argv: Sequence[str] | None = None) -> int:
        debug = os.environ.get("ROOMCAP_DEBUG", "") not in ("", "0")
        redact_log_records()
        hits = [0]
        previous = _stop_on_sigint(prog, hits)
        try:
            code = main(expand_user_args(sys.argv[1:] if argv is None else argv))
            return EXIT_OK if code is None else int(code)
        except KeyboardInterrupt:
            print(f"{prog}: interrupted; what was finished is kept (run the command again to go on).",
                  file=sys.stderr)  # fmt: skip
            if hits[0]:  # a real Ctrl-C: the work has unwound; skip the interpreter's slow teardown
                for stream in (sys.stdout, sys.stderr):
                    try:
                        stream.flush()
                    except (OSError, ValueError):
                        pass
                os._exit(EXIT_INTERRUPTED)
            return EXIT_INTERRUPTED
        except (RoomcapError, ValueError, OSError) as e:
            # ValueError: the project's bad-input errors that predate RoomcapError are ValueErrors.
            if debug:
                logging.getLogger(prog).exception("ROOMCAP_DEBUG traceback")
            text = describe_os_error(e) if isinstance(e, OSError) and e.strerror else str(e)
            print(f"{prog}: error: {redact(text)}", file=sys.stderr)
            return EXIT_INPUT
        finally:
            if previous is not None:
                signal.signal(signal.SIGINT, previous)

    run.__doc__ = main.__doc__
    run.__wrapped__ = main  # type: ignore[attr-defined]
    return run


class _DefaultsMixin(argparse.HelpFormatter):
    """Every option that takes a value shows its default: "(default: X)" is appended to its help unless the
    help already says its default."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        text = action.help or ""
        if (
            not text
            or text == argparse.SUPPRESS
            or "default" in text.lower()
            or not action.option_strings
            or action.nargs == 0
            or action.required
        ):
            return action.help
        d = action.default
        if d is None or d == "" or (isinstance(d, (list, tuple)) and not d):
            shown = "none"
        elif isinstance(d, (list, tuple)):
            shown = ",".join(map(str, d))
        else:
            shown = str(d)
        return f"{text} (default: {shown.replace('%', '%%')})"


class HelpFormatter(_DefaultsMixin, argparse.HelpFormatter):
    pass


class RawDescriptionHelpFormatter(_DefaultsMixin, argparse.RawDescriptionHelpFormatter):
    pass


class Parser(argparse.ArgumentParser):
    """The argument parser of every command: its ``--help`` (and its subcommands') names each option's
    default."""

    def __init__(self, *args: Any, **kwargs: Any) -> None:
        fmt = kwargs.get("formatter_class", argparse.HelpFormatter)
        if fmt is argparse.RawDescriptionHelpFormatter:
            kwargs["formatter_class"] = RawDescriptionHelpFormatter
        elif fmt is argparse.HelpFormatter:
            kwargs["formatter_class"] = HelpFormatter
        super().__init__(*args, **kwargs)


def _number(kind: type, low: float, inclusive: bool, what: str) -> Callable[[str], Any]:
    def parse(text: str) -> Any:
        try:
            v = kind(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not {what}") from None
        if v < low or (v == low and not inclusive):
            raise argparse.ArgumentTypeError(f"{text} is out of range: give {what}")
        return v

    parse.__name__ = what  # argparse names the type in its messages
    return parse


positive_int = _number(int, 0, False, "a whole number > 0")
nonnegative_int = _number(int, 0, True, "a whole number >= 0")
positive_float = _number(float, 0.0, False, "a number > 0")


def parse_sets(items: Sequence[str] | None) -> dict[str, str]:
    """``--set key=value`` options as a dict of strings (typed later by ``core.config.config_from_dict``).

    >>> parse_sets(["epochs=20", "lr = 1e-3"])
    {'epochs': '20', 'lr': '1e-3'}
    >>> parse_sets(["epochs"])
    Traceback (most recent call last):
    roomcap.core.errors.InputError: --set expects key=value, got 'epochs'
    """
    out = {}
    for it in items or []:
        if "=" not in it:
            raise InputError(f"--set expects key=value, got {it!r}")
        k, v = it.split("=", 1)
        out[k.strip()] = v.strip()
    return out


def output_folder(path: str | os.PathLike[str], flag: str = "--out") -> Path:
    """``path`` as a folder to write into, made if missing; a file there or no write access is an error."""
    p = Path(path)
    if p.exists() and not p.is_dir():
        raise InputError(f"{flag} {p} is a file; give a folder (it is made if missing).")
    p.mkdir(parents=True, exist_ok=True)
    if not os.access(p, os.W_OK):
        raise InputError(f"{flag} {p} is not writable; choose another folder or fix its permissions.")
    return p
