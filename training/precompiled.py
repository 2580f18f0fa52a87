"""The planar meso-ANN step (``training.fast_increment.step``) as machine code that a process loads without numba.

A process that runs this step alone then pays neither numba's import nor its set-up at the first compiled call.
``PrecompiledStep`` compiles, once per machine, a C-callable wrapper (``numba.cfunc``) of the fused step for the
argument types of ``training.inference.FastAdvance``, writes its object code to a cache file (``cache_dir``), and
in later processes loads that object with llvmlite alone (the LLVM binding numba is built on) and calls it
through ctypes: the same machine code as numba's for the same source, options and CPU, so the same bits.

The wrapper takes the address of the argument tuple and reads every argument from the CPython objects
themselves (the items of the tuples, the values of the floats, the data pointer and shape of each
C-contiguous array: ``OBJECT_OFFSETS``, checked against ctypes before the first use), so a call costs no
per-array conversion. A cache file is keyed (``step_key``) on the wrapper's argument types, the sources of
the kernels, the numba and llvmlite versions, the Python version, the host CPU and its features and every
``NUMBA_*`` setting but the cache's folder; any change compiles a new one. Where the object cannot be built or
loaded (``PrecompiledStep.reason``), ``FastAdvance`` calls numba's kernel instead (the same bits).

The object's references into numba's runtime (its raising and allocating helpers) are resolved from numba's
C extension modules, loaded without the numba package.
"""

from __future__ import annotations

import builtins
import ctypes
import functools
import hashlib
import importlib.machinery
import importlib.util
import json
import os
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

_SOURCES = ("training/fast_increment.py", "training/fast_features.py", "training/fast_cells.py",
            "training/perceptron.py", "training/fast_tables.py", "training/precompiled.py",
            "warp_hcell/core/contact.py")
"""The files whose text enters ``step_key`` (the step's kernels, their records and this wrapper)."""

_ROOT = Path(__file__).resolve().parent.parent

OBJECT_OFFSETS = np.array([tuple.__basicsize__, float.__basicsize__ - 8, object.__basicsize__,
                           object.__basicsize__ + 16], dtype=np.int64)
"""Byte offsets in CPython objects that the wrapper reads: a tuple's first item, a float's value, an
array's data pointer and its shape pointer (numpy's ``PyArrayObject``: data, then nd, then dimensions)."""

_OFFSETS_ADDRESS = OBJECT_OFFSETS.ctypes.data
"""The address of ``OBJECT_OFFSETS``'s data, passed at every call (the array lives as long as the module)."""

_HEADER = 8
"""Bytes of the cache file's first field: the length of its JSON header (then the header, then the object)."""


def _structure(value: Any) -> Any:
    """The argument types of ``value`` as JSON: an array's dtype and rank, a float, a tuple's class and items."""
    if isinstance(value, np.ndarray):
        return ["array", value.dtype.str, value.ndim]
    if isinstance(value, float):
        return ["float"]
    if isinstance(value, tuple):
        kind = type(value)
        name = "tuple" if kind is tuple else f"{kind.__module__}:{kind.__qualname__}"
        return [name, [_structure(item) for item in value]]
    raise TypeError(f"the precompiled step takes arrays, floats and tuples, not {type(value).__name__}")


def step_key(args: tuple) -> tuple[str, dict]:
    """(sha256 hex digest, the fields hashed) of the object that serves ``args`` (``FastAdvance``'s fused-step
    arguments) on this machine."""
    fields = {
        "structure": _structure(args),
        **_machine(),
        "numba_env": {k: v for k, v in sorted(os.environ.items())
                      if k.startswith("NUMBA_") and k != "NUMBA_CACHE_DIR"},
    }
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest(), fields


@functools.lru_cache(maxsize=1)
def _machine() -> dict[str, Any]:
    """The fields of ``step_key`` that a process does not change: the sources' digests, the versions, the CPU (read
    once per process, as numba reads its kernels' sources once)."""
    import llvmlite  # noqa: PLC0415
    import llvmlite.binding as ll  # noqa: PLC0415

    return {
        "sources": {name: hashlib.sha256((_ROOT / name).read_bytes()).hexdigest() for name in _SOURCES},
        "numba": hashlib.sha256((_numba_root() / "_version.py").read_bytes()).hexdigest(),
        "llvmlite": llvmlite.__version__,
        "python": sys.version,
        "triple": ll.get_process_triple(),
        "cpu": ll.get_host_cpu_name(),
        "features": ll.get_host_cpu_features().flatten(),
    }


def cache_dir() -> Path:
    """Where the objects are kept: ``$NUMBA_CACHE_DIR/precompiled`` where that is set (numba's own cache setting),
    else ``training/__pycache__/precompiled`` where writable, else ``$XDG_CACHE_HOME/warp_hcell/precompiled``
    (``~/.cache`` without it)."""
    numba_dir = os.environ.get("NUMBA_CACHE_DIR")
    if numba_dir:
        return Path(numba_dir) / "precompiled"
    beside = Path(__file__).resolve().parent / "__pycache__"
    try:
        beside.mkdir(exist_ok=True)
        if os.access(beside, os.W_OK):
            return beside / "precompiled"
    except OSError:
        pass
    return Path(os.environ.get("XDG_CACHE_HOME") or Path.home() / ".cache") / "warp_hcell" / "precompiled"


def _wrapper_source(structure: list) -> str:
    """The Python source of the cfunc ``wrapper(root, offsets)``: every argument read from the tuple at address
    ``root`` (``OBJECT_OFFSETS``), then ``step`` called on them."""
    lines: list[str] = []
    dtypes = {"<f8": "np.float64", "<f4": "np.float32", "<i8": "np.int64", "|b1": "np.bool_"}

    def read(node, address: str) -> str:
        name = f"v{len(lines)}"
        kind = node[0]
        if kind == "array":
            shape = ", ".join(f"load(load({address} + offsets[3]) + {8 * k})" for k in range(node[2]))
            data = f"as_pointer(load({address} + offsets[2]))"
            lines.append(f"    {name} = numba.carray({data}, ({shape},), {dtypes[node[1]]})")
            return name
        if kind == "float":
            lines.append(f"    {name} = load_float({address} + offsets[1])")
            return name
        lines.append(f"    {name} = {address}")
        items = [read(item, f"load({name} + offsets[0] + {8 * k})") for k, item in enumerate(node[1])]
        return f"({', '.join(items)},)" if kind == "tuple" else f"{kind.split(':')[1]}({', '.join(items)})"

    call = read(["tuple", structure[1]], "root")
    return "def wrapper(root, offsets):\n" + "\n".join(lines) + f"\n    step(*{call})\n"


def _build(args: tuple) -> tuple[str, bytes, list[str]]:
    """Compile the wrapper of ``step`` for ``args`` with numba: (its symbol, its object code, the symbols it
    leaves to the loader)."""
    import numba  # noqa: PLC0415
    from llvmlite import ir  # noqa: PLC0415
    from numba import types  # noqa: PLC0415
    from numba.extending import intrinsic  # noqa: PLC0415

    from training.fast_increment import step  # noqa: PLC0415

    def loader(result):
        def typer(typingctx, address):
            def codegen(context, builder, signature, arguments):
                pointer = builder.inttoptr(arguments[0], context.get_value_type(result).as_pointer())
                return builder.load(pointer)
            return result(types.int64), codegen
        return intrinsic(typer)

    @intrinsic
    def as_pointer(typingctx, address):
        def codegen(context, builder, signature, arguments):
            return builder.inttoptr(arguments[0], ir.IntType(8).as_pointer())
        return types.voidptr(types.int64), codegen

    structure = _structure(args)
    namespace = {"np": np, "numba": numba, "step": step, "as_pointer": as_pointer, "load": loader(types.int64),
                 "load_float": loader(types.float64)}
    for node in structure[1]:
        if node[0] not in ("array", "float", "tuple"):
            module, name = node[0].split(":")
            namespace[name] = getattr(importlib.import_module(module), name)
    exec(_wrapper_source(structure), namespace)  # noqa: S102 (source generated above from argument types)
    compiled = numba.cfunc(types.void(types.int64, types.CPointer(types.int64)), error_model="numpy")(
        namespace["wrapper"])
    library = compiled._library  # numba's code library of the cfunc: its final LLVM module and target machine
    module = library._final_module
    code = library._codegen._tm.emit_object(module)
    declared = {f.name for f in module.functions if f.is_declaration and not f.name.startswith("llvm.")}
    declared |= {g.name for g in module.global_variables if g.is_declaration}
    return compiled.native_name, code, sorted(declared | _undefined_symbols(code))


def _undefined_symbols(code: bytes) -> set[str]:
    """The undefined symbols of an ELF64 little-endian object ``code`` (those its code generation added to the
    module's declarations, such as ``memset``); empty for another format."""
    import struct  # noqa: PLC0415 (building only)

    if code[:4] != b"\x7fELF" or code[4] != 2 or code[5] != 1:
        return set()
    section_offset, = struct.unpack_from("<Q", code, 0x28)
    entry_size, count = struct.unpack_from("<HH", code, 0x3A)
    sections = [struct.unpack_from("<IIQQQQIIQQ", code, section_offset + k * entry_size) for k in range(count)]
    names = set()
    for kind, link, offset, size, entsize in ((s[1], s[6], s[4], s[5], s[9]) for s in sections):
        if kind != 2:  # SHT_SYMTAB
            continue
        strings = sections[link][4]
        for start in range(offset + entsize, offset + size, entsize):  # entry 0 is the null symbol
            name, info, _, index = struct.unpack_from("<IBBH", code, start)
            if index == 0 and name:  # SHN_UNDEF
                end = code.index(b"\0", strings + name)
                names.add(code[strings + name:end].decode())
    return names


def _numba_root() -> Path:
    """The folder of the numba package (found, not imported)."""
    return Path(importlib.util.find_spec("numba").origin).parent


def _numba_helpers(symbols: list[str]) -> dict[str, int]:
    """Addresses of numba's C helpers by their symbols: ``numba_*`` and the C math functions (``numba._helperlib``,
    as numba binds them) and ``NRT_*`` (``numba.core.runtime._nrt_python``), for the extension modules that
    ``symbols`` need, loaded alone where numba is not imported (no Python of the numba package runs)."""
    def extension(name: str):
        if name in sys.modules:
            return sys.modules[name]
        relative = _numba_root().joinpath(*name.split(".")[1:])
        path = next(p for p in (Path(f"{relative}{s}") for s in importlib.machinery.EXTENSION_SUFFIXES) if p.exists())
        module_spec = importlib.util.spec_from_file_location(name, path)
        module = importlib.util.module_from_spec(module_spec)
        module_spec.loader.exec_module(module)
        if name.endswith("_nrt_python"):
            module.memsys_use_cpython_allocator()  # as numba's import does: the kernels' temporaries through CPython's
        return module

    helpers: dict[str, int] = {}
    helper_lib = extension("numba._helperlib").c_helpers
    helpers.update({f"numba_{k}": v for k, v in helper_lib.items()})
    helpers.update(helper_lib)
    if any(symbol.startswith("NRT_") for symbol in symbols):
        helpers.update({f"NRT_{k}": v for k, v in extension("numba.core.runtime._nrt_python").c_helpers.items()
                        if not k.startswith("_")})
    if "numba_make_generator" in symbols:
        helpers.update({f"numba_{k}": v for k, v in extension("numba._dynfunc").c_helpers.items()})
    return helpers


class _Loader:
    """llvmlite's MCJIT engine holding the loaded objects of this process (their code lives as long as it)."""

    def __init__(self) -> None:
        import llvmlite.binding as ll  # noqa: PLC0415

        ll.initialize_native_target()
        ll.initialize_native_asmprinter()
        self._ll = ll
        machine = ll.Target.from_default_triple().create_target_machine()
        self._engine = ll.create_mcjit_compiler(ll.parse_assembly(""), machine)
        self._helpers: dict[str, int] = {}
        self._process = ctypes.CDLL(None)

    def _address(self, symbol: str) -> int | None:
        """The address of ``symbol``: numba's helpers first, then this process's own symbols (CPython's, libc's)."""
        if symbol in self._helpers:
            return self._helpers[symbol]
        if symbol == "_Py_NoneStruct":
            return id(None)
        if symbol.startswith("PyExc_") and isinstance(getattr(builtins, symbol[6:], None), type):
            return id(getattr(builtins, symbol[6:]))
        try:
            return ctypes.cast(getattr(self._process, symbol), ctypes.c_void_p).value
        except AttributeError:
            return None

    def load(self, name: str, code: bytes, external: list[str]):
        """The ctypes function ``name`` of the object ``code`` (ValueError where a symbol of ``external`` is not
        found: nothing is loaded then)."""
        ll = self._ll
        self._helpers.update(_numba_helpers(external))
        addresses = {symbol: self._address(symbol) for symbol in external}
        missing = [symbol for symbol, address in addresses.items() if not address]
        if missing:
            raise ValueError(f"symbols not found: {', '.join(missing)}")
        for symbol, address in addresses.items():
            ll.add_symbol(symbol, address)
        self._engine.add_object_file(ll.ObjectFileRef.from_data(code))
        self._engine.finalize_object()
        address = self._engine.get_function_address(name)
        if not address:
            raise ValueError(f"the object has no function {name}")
        return ctypes.CFUNCTYPE(None, ctypes.c_int64, ctypes.c_void_p)(address)


_LOADER: _Loader | None = None
_LOADED: dict[str, Any] = {}
"""The loaded steps of this process by ``step_key`` (an object is loaded once)."""
_LOCK = threading.Lock()


def _offsets_agree() -> bool:
    """Whether ``OBJECT_OFFSETS`` read a tuple's items, a float's value and an array's data and shape in this
    Python (through ctypes, as the wrapper reads them)."""
    array, number = np.zeros((3, 5)), 2.5
    pair = (array, number)
    read = lambda address: ctypes.c_int64.from_address(address).value  # noqa: E731
    return (read(id(pair) + int(OBJECT_OFFSETS[0])) == id(array)
            and read(id(pair) + int(OBJECT_OFFSETS[0]) + 8) == id(number)
            and ctypes.c_double.from_address(id(number) + int(OBJECT_OFFSETS[1])).value == number
            and read(id(array) + int(OBJECT_OFFSETS[2])) == array.ctypes.data
            and [read(read(id(array) + int(OBJECT_OFFSETS[3])) + 8 * k) for k in range(2)] == [3, 5])


class PrecompiledStep:
    """``training.fast_increment.step`` for one argument structure, loaded from ``cache_dir`` or built there.

    Call it with the argument tuple of ``step`` (the same types as ``args``, arrays C-contiguous): it runs the
    step in place, as numba's kernel does. ``available`` is False where it could not be built or loaded
    (``reason`` says why); ``built`` says whether this process compiled it (numba imported then).

    Args:
        args: the arguments of a first call (``FastAdvance``'s fused step), for their types.
        build: compile and store the object where no cache file serves (False: only load).
    """

    def __init__(self, args: tuple, *, build: bool = True) -> None:
        self.available, self.built, self.reason = False, False, ""
        self._function = None
        if not _offsets_agree():
            self.reason = "this Python's object layout is not the one the wrapper reads"
            return
        global _LOADER
        try:
            with _LOCK:
                key, _ = step_key(args)
                if key not in _LOADED:
                    path = cache_dir() / f"step-{key}.bin"
                    stored = self._read(path)
                    if stored is None and build:
                        stored = _build(args)
                        self.built = True
                        self._write(path, *stored)
                    if stored is None:
                        self.reason = f"no precompiled step in {path.parent}"
                        return
                    _LOADER = _LOADER or _Loader()
                    _LOADED[key] = _LOADER.load(*stored)
                self._function = _LOADED[key]
        except Exception as error:  # noqa: BLE001 (any failure: numba's kernel runs instead, the same bits)
            self.reason = f"{type(error).__name__}: {error}"
            return
        self.available = True

    @staticmethod
    def _read(path: Path) -> tuple[str, bytes, list[str]] | None:
        """(symbol, object code, external symbols) of the cache file ``path``, or None where there is none or it is
        damaged (its object's sha256 is in its header)."""
        try:
            data = path.read_bytes()
            length = int.from_bytes(data[:_HEADER], "little")
            header = json.loads(data[_HEADER:_HEADER + length])
            code = data[_HEADER + length:]
            if hashlib.sha256(code).hexdigest() != header["sha256"]:
                return None
            return header["name"], code, header["external"]
        except (OSError, ValueError, KeyError, TypeError):
            return None

    @staticmethod
    def _write(path: Path, name: str, code: bytes, external: list[str]) -> None:
        """The cache file ``path``, written whole or not at all (a temporary file renamed); nothing where the folder
        cannot be written."""
        import tempfile  # noqa: PLC0415 (building only)

        header = json.dumps({"name": name, "external": external, "sha256": hashlib.sha256(code).hexdigest()}).encode()
        try:
            path.parent.mkdir(parents=True, exist_ok=True)
            with tempfile.NamedTemporaryFile(dir=path.parent, prefix=".step-", delete=False) as handle:
                handle.write(len(header).to_bytes(_HEADER, "little") + header + code)
            os.chmod(handle.name, 0o644)
            os.replace(handle.name, path)
        except OSError:  # a cache that cannot be written: this process uses the object all the same
            pass

    def __call__(self, args: tuple) -> None:
        self._function(id(args), _OFFSETS_ADDRESS)
