"""The fused meso-ANN step (``training.fast_increment.step``, ``training.fast_step3d.step3d``) as machine code that a
process loads without numba.

A process that runs this step alone then pays neither numba's import nor its set-up at the first compiled call.
``PrecompiledStep`` compiles, once per machine, a C-callable wrapper (``numba.cfunc``) of the fused step for the
argument types of ``training.inference.FastAdvance``, writes its object code to a cache file (``cache_dir``), and
in later processes loads that object without numba and calls it through ctypes: the same machine code as numba's
for the same source, options and CPU, so the same bits.

The wrapper takes the address of the argument tuple and reads every argument from the CPython objects
themselves (the items of the tuples, the values of the floats, the data pointer and shape of each
C-contiguous array: ``OBJECT_OFFSETS``, checked against ctypes before the first use), so a call costs no
per-array conversion. A cache file is keyed (``step_key``) on the wrapper's argument types, the sources of
the kernels, the numba and llvmlite versions, the Python version, the host CPU and its features and every
``NUMBA_*`` setting but the cache's folder; any change compiles a new one. Where the object cannot be built or
loaded (``PrecompiledStep.reason``), ``FastAdvance`` calls numba's kernel instead (the same bits).

The object's references into numba's runtime (its raising and allocating helpers) are resolved from numba's
C extension modules, loaded without the numba package. On x86-64 Linux the object is mapped by this module itself
(``map_object``: its sections copied into one anonymous mapping, its relocations applied, the code made
executable), so that llvmlite is not imported; elsewhere, or where the object holds something that
``map_object`` does not support, llvmlite's MCJIT engine loads it (``PrecompiledStep.loader`` says which).
"""

from __future__ import annotations

import builtins
import ctypes
import functools
import hashlib
import importlib.machinery
import importlib.util
import json
import mmap
import os
import sys
import threading
from pathlib import Path
from typing import Any

import numpy as np

_SOURCES = ("training/fast_increment.py", "training/fast_features.py", "training/fast_cells.py",
            "training/fast_step3d.py", "training/perceptron.py", "training/fast_tables.py", "training/precompiled.py",
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


PLANAR_STEP = "training.fast_increment:step"
"""The planar fused step, ``PrecompiledStep``'s default kernel (the spatial one: ``training.fast_step3d:step3d``)."""


def step_key(args: tuple, kernel: str = PLANAR_STEP) -> tuple[str, dict]:
    """(sha256 hex digest, the fields hashed) of the object that serves ``args`` (``FastAdvance``'s fused-step
    arguments) with ``kernel`` ("module:name") on this machine."""
    fields = {
        "kernel": kernel,
        "structure": _structure(args),
        **_machine(),
        "numba_env": {k: v for k, v in sorted(os.environ.items())
                      if k.startswith("NUMBA_") and k != "NUMBA_CACHE_DIR"},
    }
    return hashlib.sha256(json.dumps(fields, sort_keys=True).encode()).hexdigest(), fields


@functools.lru_cache(maxsize=1)
def _machine() -> dict[str, Any]:
    """The fields of ``step_key`` that a process does not change: the sources' digests, the versions, the CPU (read
    once per process, as numba reads its kernels' sources once; neither numba nor llvmlite imported)."""
    return {
        "sources": {name: hashlib.sha256((_ROOT / name).read_bytes()).hexdigest() for name in _SOURCES},
        "numba": hashlib.sha256((_package_root("numba") / "_version.py").read_bytes()).hexdigest(),
        "llvmlite": hashlib.sha256((_package_root("llvmlite") / "_version.py").read_bytes()).hexdigest(),
        "python": sys.version,
        "platform": [sys.platform, os.uname().machine if hasattr(os, "uname") else ""],
        "cpu": _host_cpu(),
    }


_CPU_FIELDS = ("vendor_id", "cpu family", "model", "model name", "stepping", "flags",
               "CPU implementer", "CPU architecture", "CPU variant", "CPU part", "CPU revision", "Features")
"""The fields of the first processor in ``/proc/cpuinfo`` that say which CPU and instruction set it is (what
numba's code generation reads through LLVM's host detection), not its clock or its place in the machine."""


def _host_cpu() -> dict[str, str]:
    """The host CPU's identity and features: ``_CPU_FIELDS`` of ``/proc/cpuinfo`` where it has them, else LLVM's
    host CPU name and features (llvmlite imported then)."""
    try:
        with open("/proc/cpuinfo", encoding="utf-8", errors="replace") as handle:
            first = handle.read(1 << 16).split("\n\n", 1)[0]
        fields = dict(line.split(":", 1) for line in first.splitlines() if ":" in line)
        found = {key.strip(): value.strip() for key, value in fields.items() if key.strip() in _CPU_FIELDS}
        if found:
            return found
    except OSError:
        pass
    import llvmlite.binding as ll  # noqa: PLC0415 (no /proc/cpuinfo)

    return {"triple": ll.get_process_triple(), "cpu": ll.get_host_cpu_name(),
            "features": ll.get_host_cpu_features().flatten()}


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


def _build(args: tuple, kernel: str) -> tuple[str, bytes, list[str]]:
    """Compile the wrapper of ``kernel`` ("module:name") for ``args`` with numba: (its symbol, its object code, the
    symbols it leaves to the loader)."""
    import numba  # noqa: PLC0415
    from llvmlite import ir  # noqa: PLC0415
    from numba import types  # noqa: PLC0415
    from numba.extending import intrinsic  # noqa: PLC0415

    module, name = kernel.split(":")
    step = getattr(importlib.import_module(module), name)

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
    if code[:4] != b"\x7fELF" or code[4:6] != b"\x02\x01":
        return set()
    _, symbols, names = _elf_tables(code)
    return {names[k] for k in np.flatnonzero((symbols["shndx"] == 0) & (symbols["name"] != 0))}


def _package_root(name: str) -> Path:
    """The folder of the installed package ``name`` (found, not imported)."""
    return Path(importlib.util.find_spec(name).origin).parent


def _numba_helpers(symbols: list[str]) -> dict[str, int]:
    """Addresses of numba's C helpers by their symbols: ``numba_*`` and the C math functions (``numba._helperlib``,
    as numba binds them) and ``NRT_*`` (``numba.core.runtime._nrt_python``), for the extension modules that
    ``symbols`` need, loaded alone where numba is not imported (no Python of the numba package runs)."""
    def extension(name: str):
        if name in sys.modules:
            return sys.modules[name]
        relative = _package_root("numba").joinpath(*name.split(".")[1:])
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


def _symbol_address(symbol: str, helpers: dict[str, int]) -> int | None:
    """The address of ``symbol``: numba's ``helpers`` first, then this process's own symbols (CPython's, libc's)."""
    if symbol in helpers:
        return helpers[symbol]
    if symbol == "_Py_NoneStruct":
        return id(None)
    if symbol.startswith("PyExc_") and isinstance(getattr(builtins, symbol[6:], None), type):
        return id(getattr(builtins, symbol[6:]))
    try:
        return ctypes.cast(getattr(_process(), symbol), ctypes.c_void_p).value
    except AttributeError:
        return None


@functools.lru_cache(maxsize=1)
def _process() -> ctypes.CDLL:
    """This process's own symbols (the executable's and the libraries loaded with it)."""
    return ctypes.CDLL(None, use_errno=True)


_SECTION = np.dtype([("name", "<u4"), ("type", "<u4"), ("flags", "<u8"), ("addr", "<u8"), ("offset", "<u8"),
                     ("size", "<u8"), ("link", "<u4"), ("info", "<u4"), ("align", "<u8"), ("entsize", "<u8")])
_SYMBOL = np.dtype([("name", "<u4"), ("info", "u1"), ("other", "u1"), ("shndx", "<u2"), ("value", "<u8"),
                    ("size", "<u8")])
_RELA = np.dtype([("offset", "<u8"), ("info", "<u8"), ("addend", "<i8")])
_RELOCATIONS = {1: (8, False), 24: (8, True), 2: (4, True), 4: (4, True)}
"""x86-64 relocation types ``map_object`` applies, as (width in bytes, relative to the place): R_X86_64_64,
R_X86_64_PC64, R_X86_64_PC32, R_X86_64_PLT32."""
_MAPPINGS: list[Any] = []
"""The mappings of this process's mapped objects (their code lives as long as the process)."""


def _aligned(offset: int, alignment: int) -> int:
    """The first multiple of ``alignment`` (at least 1) at or after ``offset``."""
    return -(-offset // max(alignment, 1)) * max(alignment, 1)


def _elf_tables(code: bytes) -> tuple[np.ndarray, np.ndarray, list[str]]:
    """(section headers, symbol table, the symbols' names) of the ELF64 little-endian object ``code``."""
    sections = np.frombuffer(code, _SECTION, count=int.from_bytes(code[60:62], "little"),
                             offset=int.from_bytes(code[40:48], "little"))
    (symtab,) = [s for s in sections if s["type"] == 2]
    symbols = np.frombuffer(code, _SYMBOL, count=int(symtab["size"]) // _SYMBOL.itemsize, offset=int(symtab["offset"]))
    strings = int(sections[symtab["link"]]["offset"])
    names = [code[strings + n:code.index(b"\0", strings + n)].decode() if n else "" for n in symbols["name"]]
    return sections, symbols, names


def map_object(code: bytes, name: str, external: dict[str, int]) -> int:
    """The address of the function ``name`` of the x86-64 ELF relocatable object ``code``, mapped into this process.

    The object's allocated sections are copied into one anonymous mapping (code and constants first, then a
    zeroed writable part for its common symbols), its relocations into them applied (``_RELOCATIONS``), its
    undefined symbols taken from ``external`` (name -> address), and the first part made read-only and
    executable. Unwinding tables are not mapped (the step raises no C++ exception).

    Raises:
        ValueError: ``code`` is not an x86-64 ELF relocatable object, or holds a writable or thread-local section,
            a relocation of another type or out of its range, a symbol not in ``external``, or no ``name``.
        OSError: the mapping cannot be made executable. Nothing stays mapped after an error.
    """
    if (code[:4] != b"\x7fELF" or code[4:6] != b"\x02\x01" or int.from_bytes(code[16:18], "little") != 1
            or int.from_bytes(code[18:20], "little") != 62 or not sys.platform.startswith("linux")):
        raise ValueError("not an x86-64 ELF relocatable object on Linux")
    sections, symbols, names = _elf_tables(code)
    place: dict[int, int] = {}  # section index -> its offset in the mapping
    size = 0
    for k, section in enumerate(sections):
        if not section["flags"] & 2 or section["type"] == 0x70000001:  # not allocated; x86-64 unwinding tables
            continue
        if section["type"] != 1 or section["flags"] & 0x401 or section["align"] > mmap.PAGESIZE:
            raise ValueError(f"section {k} of type {section['type']}, flags {section['flags']:#x}, alignment "
                             f"{section['align']}")  # PROGBITS only, neither writable nor thread-local
        size = _aligned(size, int(section["align"]))
        place[k] = size
        size += int(section["size"])
    commons = np.flatnonzero(symbols["shndx"] == 0xFFF2)  # SHN_COMMON: value is the alignment
    common_at, writable = [], 0
    for index in commons:
        writable = _aligned(writable, int(symbols["value"][index]))
        common_at.append(writable)
        writable += int(symbols["size"][index])
    executable = _aligned(size, mmap.PAGESIZE)
    mapping = mmap.mmap(-1, executable + _aligned(max(writable, 1), mmap.PAGESIZE),
                        mmap.MAP_PRIVATE | mmap.MAP_ANONYMOUS, mmap.PROT_READ | mmap.PROT_WRITE)
    pinned = ctypes.c_char.from_buffer(mapping)
    base = ctypes.addressof(pinned)
    try:
        address = np.full(len(symbols), -1, dtype=np.int64)  # -1: not resolvable (in a section not mapped)
        address[0] = 0
        for index, offset in zip(commons, common_at):
            address[index] = base + executable + offset
        for index in np.flatnonzero(symbols["shndx"] == 0xFFF1):  # SHN_ABS
            address[index] = symbols["value"][index]
        for k, offset in place.items():
            inside = symbols["shndx"] == k
            address[inside] = base + offset + symbols["value"][inside].astype(np.int64)
        for index in np.flatnonzero((symbols["shndx"] == 0) & (symbols["name"] != 0)):
            if names[index] not in external:
                raise ValueError(f"symbol not found: {names[index]}")
            address[index] = external[names[index]]
        image = np.frombuffer(mapping, dtype=np.uint8)
        for k, offset in place.items():
            start = int(sections[k]["offset"])
            image[offset:offset + int(sections[k]["size"])] = np.frombuffer(code, np.uint8, int(sections[k]["size"]), start)
        for rela in (s for s in sections if s["type"] == 4 and s["info"] in place):
            entries = np.frombuffer(code, _RELA, count=int(rela["size"]) // _RELA.itemsize, offset=int(rela["offset"]))
            kinds, target = entries["info"] & 0xFFFFFFFF, (entries["info"] >> 32).astype(np.int64)
            at = place[int(rela["info"])] + entries["offset"].astype(np.int64)
            if np.any(address[target] < 0):
                raise ValueError("a relocation refers to a section that is not mapped")
            for kind in np.unique(kinds):
                if int(kind) not in _RELOCATIONS:
                    raise ValueError(f"relocation type {kind}")
                width, relative = _RELOCATIONS[int(kind)]
                chosen = kinds == kind
                if np.any(entries["offset"][chosen] + width > sections[rela["info"]]["size"]):
                    raise ValueError("a relocation lies outside its section")
                value = address[target[chosen]] + entries["addend"][chosen] - (base + at[chosen] if relative else 0)
                if width == 4 and np.any((value < -2**31) | (value >= 2**31)):
                    raise ValueError("a 32-bit relocation out of range")
                data = value.astype("<i8" if width == 8 else "<i4").view(np.uint8).reshape(-1, width)
                image[at[chosen][:, None] + np.arange(width)] = data
        entry = [i for i, n in enumerate(names) if n == name and symbols["shndx"][i] in place]
        if not entry:
            raise ValueError(f"the object has no function {name}")
        libc = _process()
        libc.mprotect.argtypes = (ctypes.c_void_p, ctypes.c_size_t, ctypes.c_int)
        if executable and libc.mprotect(base, executable, mmap.PROT_READ | mmap.PROT_EXEC) != 0:
            raise OSError(ctypes.get_errno(), "the mapped object cannot be made executable")
    except BaseException:
        image = pinned = None  # the views of the mapping go before it is unmapped
        mapping.close()
        raise
    del image  # no writable view of code that is now executable
    _MAPPINGS.append((mapping, pinned))
    return int(address[entry[0]])


class _Loader:
    """llvmlite's MCJIT engine holding the loaded objects of this process (their code lives as long as it)."""

    def __init__(self) -> None:
        import llvmlite.binding as ll  # noqa: PLC0415

        ll.initialize_native_target()
        ll.initialize_native_asmprinter()
        self._ll = ll
        machine = ll.Target.from_default_triple().create_target_machine()
        self._engine = ll.create_mcjit_compiler(ll.parse_assembly(""), machine)

    def load(self, name: str, code: bytes, external: dict[str, int]) -> int:
        """The address of the function ``name`` of the object ``code`` (ValueError where there is none), its
        undefined symbols taken from ``external``."""
        for symbol, address in external.items():
            self._ll.add_symbol(symbol, address)
        self._engine.add_object_file(self._ll.ObjectFileRef.from_data(code))
        self._engine.finalize_object()
        address = self._engine.get_function_address(name)
        if not address:
            raise ValueError(f"the object has no function {name}")
        return address


def _load(name: str, code: bytes, symbols: list[str]) -> tuple[Any, str]:
    """(the ctypes function ``name`` of the object ``code``, the loader that loaded it: "mapped" or "llvmlite: "
    and why not mapped); ValueError where a symbol of ``symbols`` is not found (nothing is loaded then)."""
    global _LOADER
    helpers = _numba_helpers(symbols)
    external = {symbol: _symbol_address(symbol, helpers) for symbol in symbols}
    missing = [symbol for symbol, address in external.items() if not address]
    if missing:
        raise ValueError(f"symbols not found: {', '.join(missing)}")
    try:
        address, loader = map_object(code, name, external), "mapped"
    except (ValueError, OSError) as error:
        _LOADER = _LOADER or _Loader()
        address, loader = _LOADER.load(name, code, external), f"llvmlite: {error}"
    return ctypes.CFUNCTYPE(None, ctypes.c_int64, ctypes.c_void_p)(address), loader


_LOADER: _Loader | None = None
_LOADED: dict[str, tuple[Any, str]] = {}
"""The loaded steps of this process and their loaders by ``step_key`` (an object is loaded once)."""
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
    """A fused step (``kernel``) for one argument structure, loaded from ``cache_dir`` or built there.

    Call it with the argument tuple of ``step`` (the same types as ``args``, arrays C-contiguous): it runs the
    step in place, as numba's kernel does. ``available`` is False where it could not be built or loaded
    (``reason`` says why); ``built`` says whether this process compiled it (numba imported then); ``loader``
    which loader loaded it ("mapped": ``map_object``; "llvmlite: " and why not mapped).

    Args:
        args: the arguments of a first call (``FastAdvance``'s fused step), for their types.
        build: compile and store the object where no cache file serves (False: only load).
        kernel: the step, "module:name": ``PLANAR_STEP`` or ``training.fast_step3d:step3d``.
    """

    def __init__(self, args: tuple, *, build: bool = True, kernel: str = PLANAR_STEP) -> None:
        self.available, self.built, self.reason, self.loader = False, False, "", ""
        self._function = None
        if not _offsets_agree():
            self.reason = "this Python's object layout is not the one the wrapper reads"
            return
        try:
            with _LOCK:
                key, _ = step_key(args, kernel)
                if key not in _LOADED:
                    path = cache_dir() / f"step-{key}.bin"
                    stored = self._read(path)
                    if stored is None and build:
                        stored = _build(args, kernel)
                        self.built = True
                        self._write(path, *stored)
                    if stored is None:
                        self.reason = f"no precompiled step in {path.parent}"
                        return
                    _LOADED[key] = _load(*stored)
                self._function, self.loader = _LOADED[key]
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
