"""Shared command-line plumbing of the command modules: the parser class, parent parsers,
validators, output (progress bars and status lines). Library code does not import it: it raises
``warp_hcell.core.errors.UserError`` and reports progress through a callback (``ProgressBar``
draws one).

Every entry point builds its parser with ``command_parser(MODULE, description)``: a ``Parser``
named ``command_prog(MODULE)``, with ``common_parser()`` (or ``verbosity_parser()`` where
--device, --seed and --overwrite do not apply) and its defaults shown, validates values
with the ``type=`` functions below, and runs its body through ``run_main``. Every bad
command line (unknown option, missing or malformed value, conflicting flags) is one line on
stderr that names the flag and the fix, exit code 2 (``Parser.error``); a ``UserError`` or
``ValueError`` of the body (bad files, inconsistent options) is also one line and exit code 2,
never a traceback. Set ``HMODEL_DEBUG=1`` to get the traceback anyway. ``--help`` is the
full help. The program name is the command the user typed: ``hmodel COMMAND`` under the
``hmodel`` script (``invoked_as``), ``python -m MODULE`` otherwise.

Output: -q/--quiet and -v/--verbose mean the same in every command (``set_verbosity``):
quiet drops the progress bars (``progress_bar``) and the status lines (``say``), verbose
lets Warp print its start-up messages, which ``quiet_warp`` otherwise silences.

``--device`` is checked while parsing (``device_name``): a CUDA device that this machine
does not have is one line and exit code 2 before any work. Output files and folders:
``warp_hcell.core.files``; ``writing_to(path)`` makes a failed write one line.
"""

from __future__ import annotations

import argparse
import contextvars
import ctypes
import ctypes.util
import difflib
import functools
import math
import os
import re
import sys
import warnings
from contextlib import contextmanager
from dataclasses import fields
from pathlib import Path
from typing import Any, Callable, Iterator, NoReturn, Sequence

from tqdm import tqdm

from warp_hcell.core.errors import EXIT_INTERRUPTED, EXIT_USAGE, UserError
from warp_hcell.core.parameters import CONTACT_LAWS, CellDefaults, check_alpha0_deg, ContactLaw, Law

@contextmanager
def writing_to(path: Path) -> Iterator[None]:
    """Turn an ``OSError`` of the body into the one-line ``UserError`` "cannot write to PATH: why"."""
    try:
        yield
    except OSError as exc:
        raise UserError(f"cannot write to {path}: {exc.strerror or exc}") from None


_INVOKED_AS: contextvars.ContextVar[str | None] = contextvars.ContextVar("invoked_as", default=None)


@contextmanager
def invoked_as(prog: str) -> Iterator[None]:
    """Name the command ``prog`` (e.g. "hmodel train") in the help, usage and error lines of
    the entry points run in the body (``command_prog``, ``run_main``)."""
    token = _INVOKED_AS.set(prog)
    try:
        yield
    finally:
        _INVOKED_AS.reset(token)


def command_prog(module: str) -> str:
    """Program name of the entry point in ``module``: the ``invoked_as`` name, else ``python -m MODULE``."""
    return _INVOKED_AS.get() or f"python -m {module}"


def _started_as(function: Callable) -> str:
    """How this process was started to run ``function``: ``python -m MODULE`` with the module the
    user typed (an entry point over ``function``'s module), else the script's name."""
    spec = getattr(sys.modules.get("__main__"), "__spec__", None)
    if spec is not None and spec.name != "__main__":
        return f"python -m {spec.name}"
    name = getattr(function, "__module__", None) or "__main__"
    return Path(sys.argv[0]).name if name == "__main__" else f"python -m {name}"


class _Probe(Exception):
    """An error while ``Parser`` looks for unknown options (not reported)."""


_REQUIRED = "the following arguments are required: "
_UNKNOWN = "unrecognized arguments: "


class Parser(argparse.ArgumentParser):
    """ArgumentParser of every entry point: a bad command line is ONE line on stderr, exit code 2.

    The line is ``PROG: error: <argparse's message>[; <the fix>]``. The message names the
    flag; a validator's message (``type=``) or a list of choices already says what is
    allowed, and the other kinds get a fix: the option meant (an unknown one close to a known
    one, else ``PROG --help``), the value to add (a missing option or value), one of two
    exclusive flags. No usage block. An unknown option is reported before missing required
    ones (it is the likelier typo).
    """

    _argv: list[str] | None = None
    _probing = False

    def parse_known_args(self, args=None, namespace=None):
        self._argv = list(sys.argv[1:] if args is None else args)
        return super().parse_known_args(args, namespace)

    def error(self, message: str) -> NoReturn:
        if self._probing:
            raise _Probe(message)
        message = " ".join(message.split())
        if message.startswith(_REQUIRED):
            unknown = self._unknown_arguments()
            if unknown:
                message = _UNKNOWN + " ".join(unknown)
        fix = self._fix(message)
        self.exit(EXIT_USAGE, f"{self.prog}: error: {message}" + (f"; {fix}" if fix else "") + "\n")

    def _unknown_arguments(self) -> list[str]:
        """The arguments of the last parse that match nothing, found with no argument required."""
        required = [action for action in self._actions if action.required]
        self._probing = True
        for action in required:
            action.required = False
        try:
            return super().parse_known_args(self._argv)[1]
        except (_Probe, UserError, ValueError):
            return []  # a value the real parse rejects too: its own error stands
        finally:
            self._probing = False
            for action in required:
                action.required = True

    def _fix(self, message: str) -> str | None:
        """The second half of the error line: what to do about ``message`` (None: it says so itself)."""
        see = f"see '{self.prog} --help'"
        if message.startswith(_UNKNOWN):
            first = message[len(_UNKNOWN):].split()[0]
            if not first.startswith("-"):
                return see
            names = {option.lstrip("-"): option for option in self._option_string_actions
                     if option.startswith("--") and option != "--help"}
            close = difflib.get_close_matches(first.split("=")[0].lstrip("-"), names, n=1, cutoff=0.75)
            return f"did you mean {names[close[0]]}?" if close else see
        if message.startswith(_REQUIRED):
            names = message.split(": ", 1)[1].split(", ")
            return "add " + " ".join(self._usage_of(name) for name in names)
        if message.endswith(": expected one argument"):
            return f"give it a value: {self._usage_of(message.split()[1].rstrip(':'))}"
        if " not allowed with argument " in message:
            return "give only one of them"
        if "ambiguous option: " in message:
            return "write the option in full"
        if ": invalid int value: " in message:
            return "give an integer"
        if ": invalid float value: " in message:
            return "give a number"
        return None

    def _usage_of(self, name: str) -> str:
        """``--flag METAVAR`` (or ``METAVAR`` of a positional) of the action argparse calls ``name``."""
        action = self._option_string_actions.get(name.split("/")[0])
        if action is None:
            return name
        if action.nargs == 0:
            return action.option_strings[-1]
        metavar = action.metavar or action.dest.upper()
        return f"{action.option_strings[-1]} {metavar if isinstance(metavar, str) else ' '.join(metavar)}"


def _float(text: str) -> float:
    try:
        value = float(text)
    except ValueError:
        raise argparse.ArgumentTypeError(f"{text!r} is not a number") from None
    if not math.isfinite(value):
        raise argparse.ArgumentTypeError(f"{text!r} is not finite")
    return value


def finite_float(text: str) -> float:
    """argparse type: a finite float."""
    return _float(text)


def positive_float(text: str) -> float:
    """argparse type: a finite float > 0."""
    value = _float(text)
    if value <= 0.0:
        raise argparse.ArgumentTypeError(f"{text} must be > 0")
    return value


def non_negative_float(text: str) -> float:
    """argparse type: a finite float >= 0."""
    value = _float(text)
    if value < 0.0:
        raise argparse.ArgumentTypeError(f"{text} must be >= 0")
    return value


def fraction(text: str) -> float:
    """argparse type: a finite float in [0, 1) (fabric anisotropy, imperfection)."""
    value = _float(text)
    if not 0.0 <= value < 1.0:
        raise argparse.ArgumentTypeError(f"{text} is outside [0, 1)")
    return value


def axial_strain(text: str) -> float:
    """argparse type: an axial strain [-] in (0, 1), a fraction (0.05 for 5 %)."""
    value = _float(text)
    if not 0.0 < value < 1.0:
        raise argparse.ArgumentTypeError(f"{text} is outside (0, 1): a strain is a fraction (0.05 for 5 %)")
    return value


def int_at_least(smallest: int):
    """argparse type factory: an integer >= ``smallest``."""
    def parse(text: str) -> int:
        try:
            value = int(text)
        except ValueError:
            raise argparse.ArgumentTypeError(f"{text!r} is not an integer") from None
        if value < smallest:
            raise argparse.ArgumentTypeError(f"{text} must be >= {smallest}")
        return value
    return parse


positive_int = int_at_least(1)
"""argparse type: an integer >= 1."""


def seed(text: str) -> int:
    """argparse type of --seed: an integer in [0, 2**63) (numpy's seeds are >= 0; run.h5 stores it as int64)."""
    value = int_at_least(0)(text)
    if value >= 2**63:
        raise argparse.ArgumentTypeError(f"{text} must be below 2**63")
    return value


def alpha0_deg(text: str) -> float:
    """argparse type: initial opening angle [deg] in [30, 90)."""
    try:
        return check_alpha0_deg(_float(text))
    except ValueError as exc:
        raise argparse.ArgumentTypeError(str(exc)) from None


def cuda_device_count() -> int:
    """Number of CUDA devices the driver reports (0 without a driver or GPU).

    Asks the CUDA driver library directly (``cuInit``, ``cuDeviceGetCount``) so that the
    check costs milliseconds and imports neither Warp nor torch.
    """
    for name in ("libcuda.so.1", "libcuda.so", ctypes.util.find_library("cuda")):
        if not name:
            continue
        try:
            lib = ctypes.CDLL(name)
        except OSError:
            continue
        count = ctypes.c_int(0)
        if lib.cuInit(0) != 0 or lib.cuDeviceGetCount(ctypes.byref(count)) != 0:
            return 0
        return int(count.value)
    return 0


def device_name(text: str) -> str:
    """argparse type of --device: "cpu", "cuda" or "cuda:N", checked against this machine.

    A malformed name is an argparse error; a CUDA device the machine does not have raises
    ``UserError`` out of ``parse_args`` (one line, exit code 2 through ``run_main``) before
    any heavy import or work.
    """
    name = text.strip().lower()
    if name == "cpu":
        return name
    match = re.fullmatch(r"cuda(?::(\d+))?", name)
    if match is None:
        raise argparse.ArgumentTypeError(f"{text!r} is not a device: use cpu, cuda or cuda:N")
    index = int(match.group(1) or 0)
    count = cuda_device_count()
    if count == 0:
        raise UserError(f"--device {text}: no CUDA GPU on this machine; use --device cpu")
    if index >= count:
        raise UserError(f"--device {text}: this machine has {count} CUDA GPU(s), cuda:0 to cuda:{count - 1}")
    return name


def quiet_warp(device: str = "cpu") -> None:
    """Silence Warp's start-up banner (call before anything initialises Warp).

    Recent Warp filters by ``config.log_level``, older versions by ``config.quiet``. On the
    cpu, Warp is initialised here with file descriptor 2 muted, because its native library
    prints "could not find the CUDA driver" straight to stderr on machines without a GPU;
    Python exceptions of the initialisation still propagate. With a CUDA device Warp's
    warnings stay visible.
    """
    import warp  # noqa: PLC0415 (only where the DEM runs)

    warp.config.quiet = True
    if hasattr(warp, "LOG_WARNING"):
        warp.config.log_level = warp.LOG_WARNING
    if device != "cpu":
        return
    sys.stderr.flush()
    saved = os.dup(2)
    devnull = os.open(os.devnull, os.O_WRONLY)
    try:
        os.dup2(devnull, 2)
        warp.init()
    finally:
        os.dup2(saved, 2)
        os.close(saved)
        os.close(devnull)


def task_setup(args: argparse.Namespace) -> Callable[[], None]:
    """Setup of a command's tasks (``warp_hcell.core.execution``, run in every worker): the command's
    -q, and ``quiet_warp(args.device)`` unless -v."""
    return functools.partial(_setup_task, getattr(args, "device", "cpu"), quiet=bool(args.quiet),
                             verbose=bool(args.verbose))


def _setup_task(device: str, *, quiet: bool, verbose: bool) -> None:
    _OUTPUT.quiet = quiet
    if not verbose:
        quiet_warp(device)


class DefaultsHelpFormatter(argparse.ArgumentDefaultsHelpFormatter):
    """Help that shows each flag's default, but not where there is none: a required flag, or a
    default of None (the flag's help says what leaving it out does)."""

    def _get_help_string(self, action: argparse.Action) -> str | None:
        if action.required or action.default is None:
            return action.help
        return super()._get_help_string(action)


def command_parser(module: str, description: str, *, device: bool = True) -> argparse.ArgumentParser:
    """Parser of the command ``python -m MODULE`` (``hmodel COMMAND``), named as the user typed it
    (``command_prog``), with its defaults shown and the flags every command shares:
    ``common_parser`` (--device, --seed, --overwrite and the verbosity), or with ``device``
    False ``verbosity_parser`` only."""
    parent = common_parser() if device else verbosity_parser()
    return Parser(prog=command_prog(module), description=description, parents=[parent],
                  formatter_class=DefaultsHelpFormatter, allow_abbrev=False)


def verbosity_parser() -> argparse.ArgumentParser:
    """Parent parser of -q/--quiet and -v/--verbose (exclusive; apply them with ``set_verbosity``)."""
    parser = Parser(add_help=False)
    group = parser.add_mutually_exclusive_group()
    group.add_argument("-q", "--quiet", action="store_true",
                       help="no progress bars or status lines; warnings and errors only")
    group.add_argument("-v", "--verbose", action="store_true",
                       help="also Warp's start-up messages (and the resolved settings, where the command has them)")
    return parser


def common_parser() -> argparse.ArgumentParser:
    """Parent parser with the flags most entry points share: --device, --seed, --overwrite, -q, -v."""
    parser = Parser(add_help=False, parents=[verbosity_parser()])
    parser.add_argument("--device", type=device_name, default="cpu",
                        help="compute device: cpu, or cuda / cuda:N where the machine has a GPU")
    parser.add_argument("--seed", type=seed, default=0, help="seed of every random choice (runs are bit-reproducible)")
    parser.add_argument("--overwrite", action="store_true", help="replace existing output instead of refusing")
    return parser


def add_contact_law_arguments(parser: argparse.ArgumentParser) -> None:
    """Add --radius (``CellDefaults``), --law and the flags every law of ``CONTACT_LAWS`` declares
    (``flags``, defaults from the law's fields; a flag several laws declare is added once); read them
    back with ``contact_law_from_args``."""
    parser.add_argument("--radius", type=positive_float, default=CellDefaults.radius, help="grain radius r [m]")
    shared = set.intersection(*({flag.flag for flag in law.flags} for law in CONTACT_LAWS.values()))
    kinds = " or ".join(f"{law.summary} ({', '.join(f.flag for f in law.flags if f.flag not in shared)}"
                        f"{'' if law.planar else '; 3D cells'})" for law in CONTACT_LAWS.values())
    parser.add_argument("--law", choices=tuple(CONTACT_LAWS), default=ContactLaw.name, help=f"contact law: {kinds}")
    added = set()
    for law in CONTACT_LAWS.values():
        defaults = {f.name: f.default for f in fields(law)}
        for flag in law.flags:
            if flag.flag not in added:
                added.add(flag.flag)
                parser.add_argument(flag.flag, type=positive_float if flag.positive else finite_float,
                                    default=defaults.get(flag.parameter, argparse.SUPPRESS), help=flag.help)


def contact_law_from_args(args: argparse.Namespace) -> Law:
    """The contact law of the flags added by ``add_contact_law_arguments`` (its ``from_flags`` of the
    flags it declares that ``args`` holds); ValueError (one line) for values outside the law's ranges, or a flag
    of another law set away from its default (it would be ignored)."""
    law = CONTACT_LAWS[getattr(args, "law", ContactLaw.name)]
    own = {flag.flag for flag in law.flags}
    for other in CONTACT_LAWS.values():
        defaults = {f.name: f.default for f in fields(other)}
        for flag in other.flags:
            value = getattr(args, flag.flag[2:].replace("-", "_"), None)
            if flag.flag not in own and value is not None and value != defaults.get(flag.parameter):
                raise ValueError(f"{flag.flag} is a flag of the {other.name} law, which --law {law.name} ignores; "
                                 f"that law takes {', '.join(sorted(own))}")
    values = {flag.parameter: getattr(args, flag.flag[2:].replace("-", "_"), None) for flag in law.flags}
    return law.from_flags(**{name: value for name, value in values.items() if value is not None})


def run_main(main: Callable[[Sequence[str] | None], int | None], argv: Sequence[str] | None = None) -> int:
    """Run ``main(argv)``; map user errors to one line on stderr and exit code 2.

    The line names the command the user typed: the ``invoked_as`` name (``hmodel COMMAND``),
    else, for a process started as ``python -m MODULE`` (``argv`` None), that; a call from
    Python with ``argv`` says "hmodel". The verbosity ``main`` set (``set_verbosity``) ends
    with it, and so does its format of Python warnings: one line, "PROG: warning: TEXT". Ctrl-C or
    SIGTERM is the line "interrupted" (with the ``KeyboardInterrupt``'s text: what resumes the work)
    and exit code 130.
    """
    prog = _INVOKED_AS.get() or (_started_as(main) if argv is None else "hmodel")
    _OUTPUT.command = True
    formatwarning = warnings.formatwarning
    warnings.formatwarning = lambda message, *_, **__: f"{prog}: warning: {' '.join(str(message).split())}\n"
    try:
        return int(main(argv) or 0)
    except (UserError, ValueError, FileNotFoundError) as exc:
        if os.environ.get("HMODEL_DEBUG"):
            raise
        message = " ".join(str(exc).split()) or type(exc).__name__
        print(f"{prog}: error: {message}", file=sys.stderr)
        return EXIT_USAGE
    except KeyboardInterrupt as exc:
        note = " ".join(str(exc).split())  # what resumes the work, where the command says
        print(f"{prog}: interrupted" + (f"; {note}" if note else ""), file=sys.stderr)
        return EXIT_INTERRUPTED
    finally:
        warnings.formatwarning = formatwarning
        _OUTPUT.quiet = False
        _OUTPUT.command = False


def running_command() -> bool:
    """Whether a command (``run_main``) is running in this process: process-wide policies that a library
    call must not impose on its caller (for example freezing the garbage collector's objects) apply then."""
    return _OUTPUT.command


# -- what a command prints ---------------------------------------------------------------------

PROGRESS_INTERVAL_S = 0.5
"""Shortest time between two redraws of a progress bar on a terminal [s]."""
PROGRESS_LOG_INTERVAL_S = 30.0
"""Time between two progress lines where stderr is not a terminal (a log file, a pipe) [s]."""


class _Output:
    """What this process prints: ``quiet`` drops progress bars and status lines (-q); ``command``: a
    command is running (``run_main``)."""

    quiet = False
    command = False


_OUTPUT = _Output()


def set_verbosity(args: argparse.Namespace) -> None:
    """Apply the -q/--quiet of ``args`` to ``say`` and ``progress_bar`` until ``run_main`` returns."""
    _OUTPUT.quiet = bool(getattr(args, "quiet", False))


def say(*lines: str) -> None:
    """Print status lines on stdout, unless the command runs with -q."""
    if not _OUTPUT.quiet:
        print(*lines, sep="\n", flush=True)


class _LogLines:
    """Stream for tqdm where stderr is no terminal: each redraw becomes one plain line.

    tqdm redraws in place, starting each drawing with a carriage return and padding it with
    spaces; here those are dropped and every non-empty drawing ends with a newline.
    """

    def __init__(self, stream: Any) -> None:
        self.stream = stream

    def write(self, text: str) -> None:
        line = text.replace("\r", "").rstrip()
        if line:
            self.stream.write(line + "\n")

    def flush(self) -> None:
        self.stream.flush()


def progress_bar(iterable: Any = None, *, disable: bool = False, file: Any = None, **kwargs: Any) -> tqdm:
    """A tqdm progress bar on stderr (``file``), as every command draws them.

    On a terminal it redraws in place at most every ``PROGRESS_INTERVAL_S`` (and is erased
    at the end where ``leave=False``). Elsewhere it writes plain newline-terminated lines, no
    carriage return: one at the start, one every ``PROGRESS_LOG_INTERVAL_S`` and the final
    count at the end. Disabled by ``disable`` or a command's -q (``set_verbosity``).
    ``kwargs`` go to tqdm (``total``, ``desc``, ``unit``, ...).
    """
    stream = sys.stderr if file is None else file
    disable = disable or _OUTPUT.quiet
    isatty = getattr(stream, "isatty", None)
    if isatty is not None and isatty():
        kwargs = {"mininterval": PROGRESS_INTERVAL_S, **kwargs}
        return tqdm(iterable, file=stream, disable=disable, miniters=1, **kwargs)
    kwargs.update(mininterval=PROGRESS_LOG_INTERVAL_S, maxinterval=PROGRESS_LOG_INTERVAL_S, leave=True, ascii=True)
    return tqdm(iterable, file=_LogLines(stream), disable=disable, miniters=1, **kwargs)


class ProgressBar:
    """A library function's progress callback ``(done, total) -> None`` drawn as a ``progress_bar``.

    The first call starts the bar at ``done`` of ``total``; later calls advance it to ``done``;
    it closes when ``done`` reaches ``total`` or at ``close()`` (an interrupted or stopped run).
    ``kwargs`` go to ``progress_bar`` (``desc``, ``unit``, ...).
    """

    def __init__(self, **kwargs: Any) -> None:
        self._kwargs = kwargs
        self._bar: tqdm | None = None
        self._closed = False

    def __call__(self, done: int, total: int) -> None:
        if self._closed:
            return
        if self._bar is None:
            self._bar = progress_bar(total=total, initial=done, **self._kwargs)
        else:
            self._bar.update(done - self._bar.n)
        if done >= total:
            self.close()

    def close(self) -> None:
        """Close the bar (its final line where stderr is no terminal); later calls draw nothing."""
        if self._bar is not None:
            self._bar.close()
        self._closed = True
