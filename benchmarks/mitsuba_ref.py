"""Thin helpers around Mitsuba 3, used to make reference images and to benchmark against it.

Importing this module has no side effects: Mitsuba is imported lazily inside the functions.
If Mitsuba is not installed, ``available()`` returns False and the other functions raise
``RuntimeError`` with a clear message.

Variant: ``llvm_ad_rgb`` (falls back to ``scalar_rgb`` when the LLVM backend cannot be
initialised).  The drjit LLVM backend needs libLLVM; ``DRJIT_LIBLLVM_PATH`` is set to the
Debian libLLVM 19 library (``/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1``) if it is unset and
that file exists (libLLVM 15 crashes with the installed drjit).
"""

from __future__ import annotations

import importlib.util
import os
import re
import shutil
import subprocess
import sys
import time
import xml.etree.ElementTree as ET
from pathlib import Path

LIBLLVM_PATH = "/usr/lib/x86_64-linux-gnu/libLLVM.so.19.1"
PREFERRED_VARIANTS = ("llvm_ad_rgb", "scalar_rgb")

# Largest number of samples (pixels x spp) rendered in one Mitsuba pass with a JIT
# (llvm/cuda) variant; bigger renders are split into passes of equal spp, each with its own
# seed, and averaged (keeps the wavefront's memory bounded).
MAX_SAMPLES_PER_PASS = 1 << 22

# How to install Mitsuba 3 for the comparisons (the benchmarks print it when they skip it).
INSTALL_HINT = ("install Mitsuba 3 with 'pip install mitsuba' and libLLVM for its LLVM backend "
                "with 'apt-get install libllvm19'")

_MISSING = ("Mitsuba 3 is not available (pip package 'mitsuba' not importable or no usable "
            "variant among %s); install it with 'pip install mitsuba'." % (PREFERRED_VARIANTS,))

_state = {"mi": None, "error": None}


def _mitsuba():
    """Import mitsuba, select a variant, and return the module (cached)."""
    if _state["mi"] is not None:
        return _state["mi"]
    if _state["error"] is not None:
        raise RuntimeError(_MISSING + " Cause: " + _state["error"])
    if "DRJIT_LIBLLVM_PATH" not in os.environ and os.path.exists(LIBLLVM_PATH):
        os.environ["DRJIT_LIBLLVM_PATH"] = LIBLLVM_PATH
    try:
        import mitsuba as mi
    except Exception as e:  # ImportError, or a broken install
        _state["error"] = "import mitsuba failed: %r" % (e,)
        raise RuntimeError(_MISSING + " Cause: " + _state["error"]) from e
    errors = []
    for v in PREFERRED_VARIANTS:
        try:
            mi.set_variant(v)
            _state["mi"] = mi
            return mi
        except Exception as e:
            errors.append("%s: %r" % (v, e))
    _state["error"] = "; ".join(errors)
    raise RuntimeError(_MISSING + " Cause: " + _state["error"])


def available() -> bool:
    """True if mitsuba is importable and one of the preferred variants could be set."""
    try:
        _mitsuba()
        return True
    except RuntimeError:
        return False


def variant() -> str:
    """The Mitsuba variant in use (e.g. 'llvm_ad_rgb')."""
    return _mitsuba().variant()


def version() -> str:
    return _mitsuba().__version__


# Dr.Jit's LLVM backend compiles its kernels for the host CPU (16 lanes with AVX-512, 8 with
# AVX2). For a comparison as on an AVX2-only machine, it can target Haswell with 8 lanes
# instead; Embree, which the kernels call to cast their rays, picks its own instruction set
# at run time, and limit_embree() limits it.
_ISA_TARGETS = {"avx2": (b"haswell", b"+avx,+avx2,+fma,+f16c,+bmi,+bmi2,+lzcnt,+popcnt,+sse4.2,"
                                     b"-avx512f,-avx512vl,-avx512dq,-avx512bw,-avx512cd", 8)}


def add_isa_argument(parser) -> None:
    """The benchmarks' --mitsuba-isa option (its value goes to set_isa)."""
    parser.add_argument("--mitsuba-isa", choices=["native", *_ISA_TARGETS], default="native",
                        help="avx2: Mitsuba's kernels compiled for Haswell with 8 lanes and its "
                             "Embree limited to AVX2, as on an AVX2-only machine (build ours "
                             "with MARCH=x86-64-v3 for the same)")


def _drjit_core():
    import ctypes
    import drjit as dr
    return ctypes.CDLL(os.path.join(os.path.dirname(dr.__file__), "libdrjit-core.so"))


def set_isa(isa: str) -> None:
    """Make the LLVM backend compile for `isa` ('native' or 'avx2'); call before rendering
    (kernels compiled earlier keep their target). Raises if this Dr.Jit cannot be retargeted."""
    _mitsuba()
    if isa == "native":
        return
    if isa not in _ISA_TARGETS or variant().startswith("scalar"):
        raise ValueError(f"cannot target {isa!r} with variant {variant()}")
    try:
        # jit_llvm_set_target(const char *cpu, const char *features, uint32_t vector_width)
        setter = getattr(_drjit_core(), "_Z19jit_llvm_set_targetPKcS0_j")
    except (OSError, AttributeError) as e:
        raise RuntimeError(f"this Dr.Jit build has no jit_llvm_set_target: {e}") from e
    setter(*_ISA_TARGETS[isa])


def isa() -> str:
    """The LLVM backend's target CPU and lanes, e.g. 'znver5, 16 lanes' ('' for scalar), and
    Embree's limit where limit_embree() set one ('haswell, 8 lanes, Embree max_isa=avx2')."""
    if variant().startswith("scalar"):
        return ""
    import ctypes
    core = _drjit_core()
    core._Z19jit_llvm_target_cpuv.restype = ctypes.c_char_p
    limit = f", Embree max_isa={os.environ['RBPT_EMBREE_MAX_ISA']}" if embree_limited() else ""
    return f"{core._Z19jit_llvm_target_cpuv().decode()}, {core._Z21jit_llvm_vector_widthv()} lanes{limit}"


# Embree's instruction set for each --mitsuba-isa other than native (its max_isa setting).
_EMBREE_MAX_ISA = {"avx2": "avx2"}
_SHIM_SOURCE = Path(__file__).resolve().with_name("embree_max_isa.cpp")


def embree_limited() -> bool:
    """Whether this process runs with limit_embree()'s library preloaded."""
    shim = os.environ.get("RBPT_EMBREE_SHIM", "")
    return bool(shim) and shim in os.environ.get("LD_PRELOAD", "").split(":") and bool(os.environ.get("RBPT_EMBREE_MAX_ISA"))


def limit_embree(isa: str, cache: Path, reexec: bool = True) -> str:
    """Make Mitsuba's Embree cast rays with the instruction set of `isa` ('avx2'; 'native'
    leaves Embree's own choice), as on a CPU that has no more: Mitsuba gives Embree no such
    setting, so this builds benchmarks/embree_max_isa.cpp with g++ into `cache` (once) and
    re-executes the running script (os.execve) with it preloaded, which appends
    max_isa=<isa> to the configuration Mitsuba creates its Embree device with. Call it first
    in a benchmark run from the command line, before Mitsuba is imported; with reexec False
    (a benchmark's main called from Python) it does not re-execute. Returns '' where the limit
    holds (or isa is native), else why it does not, which it also prints."""
    why = _limit_embree(isa, cache, reexec)
    if why:
        print(f"Mitsuba's Embree keeps its own instruction set: {why}")
    return why


def _limit_embree(isa: str, cache: Path, reexec: bool) -> str:
    if isa == "native" or embree_limited():
        return ""
    if isa not in _EMBREE_MAX_ISA:
        raise ValueError(f"no Embree instruction set for {isa!r}")
    spec = importlib.util.find_spec("mitsuba")
    if spec is None or not spec.submodule_search_locations:
        return "Mitsuba is not installed"
    lib = Path(list(spec.submodule_search_locations)[0]) / "libembree3.so"
    if not lib.exists():
        return f"Mitsuba has no {lib.name} here"
    if shutil.which("g++") is None:
        return "g++ is needed to build embree_max_isa.cpp"
    if not reexec:
        return "not run from the command line (the limit needs the benchmark re-executed)"
    shim = Path(cache).resolve() / "embree_max_isa.so"
    if not shim.exists() or shim.stat().st_mtime < _SHIM_SOURCE.stat().st_mtime:
        shim.parent.mkdir(parents=True, exist_ok=True)
        build = subprocess.run(["g++", "-O2", "-shared", "-fPIC", str(_SHIM_SOURCE), "-o", str(shim), "-ldl"],
                               capture_output=True, text=True)
        if build.returncode != 0:
            return f"building embree_max_isa.cpp failed: {build.stderr[-500:]}"
    preload = ":".join(p for p in (str(shim), os.environ.get("LD_PRELOAD", "")) if p)
    env = dict(os.environ, RBPT_EMBREE_SHIM=str(shim), RBPT_EMBREE_LIB=str(lib),
               RBPT_EMBREE_MAX_ISA=_EMBREE_MAX_ISA[isa], LD_PRELOAD=preload)
    print(f"re-running with Mitsuba's Embree limited to {_EMBREE_MAX_ISA[isa]} ({shim.name} preloaded)", flush=True)
    sys.stderr.flush()
    os.execve(sys.executable, [sys.executable, *sys.argv], env)


# ----------------------------------------------------------------------------- scene loading

def _inline(root: ET.Element, folder: str, search: list) -> None:
    """Recursively inline <include> elements and drop <path> elements naming missing folders.

    ``search`` is the list of folders used to resolve relative file names (Mitsuba resolves
    <include filename> and mesh file names through its file resolver, whose first entry is
    the folder of the top-level scene file)."""
    for i, child in reversed(list(enumerate(list(root)))):
        if child.tag == "path":
            p = child.get("value", "")
            full = p if os.path.isabs(p) else os.path.normpath(os.path.join(folder, p))
            root.remove(child)
            if os.path.isdir(full):
                search.insert(0, full)  # <path> prepends to the resolver, like Mitsuba does
        elif child.tag == "include":
            fn = child.get("filename", "")
            cands = [fn] if os.path.isabs(fn) else [os.path.join(d, fn) for d in search]
            cands = [c for c in cands if os.path.exists(c)]
            if not cands:
                raise FileNotFoundError("<include filename=%r>: not found in %s" % (fn, search))
            sub = ET.parse(cands[0]).getroot()
            _inline(sub, os.path.dirname(os.path.abspath(cands[0])), search)
            root.remove(child)
            for j, sc in enumerate(list(sub)):
                root.insert(i + j, sc)
        else:
            _inline(child, folder, search)


def _set_film_size(root: ET.Element, width, height) -> None:
    films = [f for s in root.iter("sensor") for f in s.findall("film")]
    if not films:
        raise ValueError("no <sensor><film> found in the scene")
    for film in films:
        for name, val in (("width", width), ("height", height)):
            if val is None:
                continue
            elems = [e for e in film if e.get("name") == name]
            if elems:
                for e in elems:
                    e.tag = "integer"
                    e.set("value", str(int(val)))
            else:
                ET.SubElement(film, "integer", {"name": name, "value": str(int(val))})


def scene_xml(path, width=None, height=None):
    """Returns (xml_text, search_folders): the XML text ``load_scene`` gives Mitsuba
    (includes inlined, <path> elements removed, film size replaced) and the folders to
    prepend to Mitsuba's file resolver (the scene's folder, then existing <path> folders)."""
    path = os.path.abspath(str(path))
    folder = os.path.dirname(path)
    root = ET.parse(path).getroot()
    search = [folder]
    _inline(root, folder, search)
    if width is not None or height is not None:
        _set_film_size(root, width, height)
    return ET.tostring(root, encoding="unicode"), search


def load_scene(path, width=None, height=None, optimize=True, **defaults):
    """Load a Mitsuba 3 XML scene file.

    ``defaults`` override the file's ``<default name=... value=...>`` parameters (values
    are converted with ``str``; names whose ``$name`` does not occur in the XML, e.g.
    ``res`` once the film size is replaced, are ignored, so a misspelt name is not an
    error).  ``<include>`` files are inlined and ``<path>`` elements that name missing
    folders are dropped (Mitsuba's loader fails on them; veach-mis has one); existing
    ``<path>`` folders and the scene's own folder are prepended to Mitsuba's file resolver
    while loading (the resolver is restored afterwards).  If ``width``/``height`` are
    given, the film's ``width``/``height`` are replaced; everything else (rfilter, fov,
    fov_axis, no crop) is kept as in the file.

    ``optimize`` is passed to ``mi.load_string``.  Mitsuba's default (True) merges meshes
    that share a BSDF (e.g. cbox's floor/ceiling/back become one ``object_<addr>`` mesh)
    and deduplicates identical BSDFs, which changes ``mi.traverse`` keys but not the image;
    use ``optimize=False`` to keep every shape id."""
    mi = _mitsuba()
    text, search = scene_xml(path, width, height)
    fr = mi.file_resolver() if hasattr(mi, "file_resolver") else \
        mi.Thread.thread().file_resolver()
    saved = [str(p) for p in fr]
    try:
        for d in reversed(search):
            fr.prepend(d)
        # Overrides whose $variable no longer occurs (e.g. $res after replacing the film
        # size) would make Mitsuba fail with "Found unused parameters": drop them.
        kwargs = {k: str(v) for k, v in defaults.items()
                  if re.search(r"\$%s\b" % re.escape(k), text)}
        return mi.load_string(text, optimize=optimize, **kwargs)
    finally:
        fr.clear()
        for p in saved:
            fr.append(p)


# ----------------------------------------------------------------------------- rendering

def _pass_seed(seed: int, i: int) -> int:
    # Distinct, well-separated seeds for the passes of one render; pass 0 uses ``seed`` itself
    # so that single-pass renders match mi.render(scene, spp=spp, seed=seed).
    return (int(seed) + i * 0x9E3779B1) & 0xFFFFFFFF


def render(scene, spp, seed=0):
    """Render the scene's first sensor with ``spp`` samples per pixel; returns a float32
    numpy array (H, W, 3) (alpha, if the film has it, is dropped).

    With a JIT variant, renders with more than ``MAX_SAMPLES_PER_PASS`` samples are split
    into equal passes (seeds derived from ``seed``), whose film sums (each pixel's filter
    weights times values, and its weights) are added up and divided once: the image one
    film taking all ``spp`` samples makes, as ``mi.render`` would with the memory for it.
    (Until session 49 the passes' normalised images were averaged, which keeps each pass's
    ratio estimate and its bias; small: cornell-box's 4096 spp reference, 64 passes of 64
    spp, moved by 8e-5 RMS, its largest pixel by 0.009.) A render of one pass is
    ``mi.render``'s image. Mitsuba's AD integrators (``prb``) refuse to render without
    developing the film, so their passes' developed images are averaged instead (each pass
    then keeps its own ratio estimate, the small bias described above: the gradient
    benchmark's fixed target images are rendered so)."""
    import numpy as np
    mi = _mitsuba()
    spp = int(spp)
    sensor = scene.sensors()[0]
    w, h = sensor.film().crop_size()
    per_pass = spp
    if not mi.variant().startswith("scalar"):
        max_spp = max(1, MAX_SAMPLES_PER_PASS // max(1, w * h))
        npass = -(-spp // max_spp)
        while spp % npass:
            npass += 1
        per_pass = spp // npass
    npass = spp // per_pass
    if npass == 1:
        img = np.asarray(mi.render(scene, spp=spp, seed=_pass_seed(seed, 0)), dtype=np.float32)
        img = img if img.ndim == 3 else img[..., None]
        return img[..., :3] if img.shape[-1] >= 3 else np.repeat(img[..., :1], 3, axis=2)
    if _is_ad_integrator(scene.integrator()):
        images = [render(scene, per_pass, seed=_pass_seed(seed, i)) for i in range(npass)]
        return np.mean(np.stack(images).astype(np.float64), axis=0).astype(np.float32)
    sums = weights = None
    for i in range(npass):
        scene.integrator().render(scene, sensor, seed=_pass_seed(seed, i), spp=per_pass, develop=False)
        raw = np.array(sensor.film().bitmap(raw=True), dtype=np.float64)  # R, G, B, [A,] W
        sums = raw[..., :3] if sums is None else sums + raw[..., :3]
        weights = raw[..., -1:] if weights is None else weights + raw[..., -1:]
    # (As the film's develop: a pixel that no sample reached is 0.)
    return np.where(weights != 0, sums / np.where(weights != 0, weights, 1.0), 0.0).astype(np.float32)


def _is_ad_integrator(integrator) -> bool:
    """Whether ``integrator`` is one of Mitsuba's AD integrators (prb and its kin: their
    Python classes derive from ``mi.CppADIntegrator``)."""
    base = getattr(_mitsuba(), "CppADIntegrator", None)
    return base is not None and isinstance(integrator, base)


def _compiled_kernels(dr) -> int:
    """Number of JIT kernels compiled (not found in drjit's memory cache) since last call."""
    n = 0
    for k in dr.kernel_history():
        if k.get("type") == dr.KernelType.JIT and not k.get("cache_hit", 1):
            n += 1
    return n


def time_render(scene, spp, seed=0, repeats=1):
    """Time ``render(scene, spp, seed)``; returns (best wall-clock seconds, image).

    JIT warm-up: the LLVM variant traces and compiles its kernels on first use; drjit
    caches them (in memory and on disk) by kernel IR.  The IR does not depend on the seed,
    but, as measured with drjit's kernel history, it does depend on the wavefront size
    class (in Mitsuba 3.9.1 / cbox: spp 1-2 share a kernel, 3 another, powers of two >= 4
    another, other spp another).  So we (1) render once, untimed, at low spp (min(spp, 4)) with
    another seed, then (2) time the render; with drjit's kernel history enabled we check
    whether the timed render still compiled a kernel and, if so, render and time it again
    (at most twice), so the reported time excludes compilation.  With ``repeats > 1``
    the minimum over repeats is returned, with the image of the last repeat.  With the
    scalar variant there is no JIT and the warm-up is skipped."""
    import drjit as dr
    mi = _mitsuba()
    jit = not mi.variant().startswith("scalar")
    if jit:
        flag = dr.flag(dr.JitFlag.KernelHistory)
        dr.set_flag(dr.JitFlag.KernelHistory, True)
        render(scene, min(int(spp), 4), seed=seed + 12345)  # warm-up (untimed)
        dr.sync_thread()
        _compiled_kernels(dr)  # clears the history
    try:
        best, img = float("inf"), None
        runs, extra = max(1, int(repeats)), 0
        i = 0
        while i < runs:
            dr.sync_thread()
            t0 = time.perf_counter()
            img = render(scene, spp, seed=seed)
            dr.sync_thread()
            dt = time.perf_counter() - t0
            if jit and _compiled_kernels(dr) and extra < 2:
                extra += 1  # this run included compilation: do not count it
                continue
            best = min(best, dt)
            i += 1
    finally:
        if jit:
            dr.set_flag(dr.JitFlag.KernelHistory, flag)
    return best, img
