"""Scenes outside bench_error_time.py's set, ours against Mitsuba 3: where a feature takes a
slower path than the benchmark scenes' (a light sampled one lane at a time, a scene the
wavefront does not take, shapes that are not tested in lanes).

    python benchmarks/bench_survey.py                  # every variant, 128 px, 64 spp
    python benchmarks/bench_survey.py --only direct4   # some of them
    python benchmarks/bench_survey.py --quick          # seconds: a smoke run

The variants are the shared cbox with one thing changed (written to
benchmarks/results/survey/, its meshes read from ../shared), and our spheres-only scene
(benchmarks/scenes/spheres.xml). For each: a reference rendered once by Mitsuba at
--ref-spp (cached there), then, in turns, ours and Mitsuba at --spp, --repeats times each
with seeds 1, 2, ... (after a warm-up render at the same spp, which compiles Mitsuba's
kernels). The table gives the median times, the mean RMSE against the reference, the time
ratio at equal spp, and the equal-error ratio: time ratio x (RMSE ratio)^2. Two threads
each (torch's default here). Needs Mitsuba 3; writes benchmarks/results/survey.csv.
"""
from __future__ import annotations

import argparse
import datetime
import statistics
import sys
import time
from pathlib import Path

import torch

HERE = Path(__file__).resolve().parent
sys.path.insert(0, str(HERE))
from machine import cpu_model, write_csv  # noqa: E402
import mitsuba_ref  # noqa: E402  (imports Mitsuba lazily)
from bench_error_time import rmse  # noqa: E402  (the error-time benchmark's metric)

CBOX = HERE.parent.parent / "shared" / "scenes" / "cbox" / "cbox.xml"
OUT = HERE / "results" / "survey"

# The cbox's light, and what the variants put in its place or beside it.
AREA = """        <emitter type="area">
            <rgb name="radiance" value="18.387, 13.9873, 6.75357"/>
        </emitter>
"""
POINT = ('    <emitter type="point"><point name="position" x="0" y="0.8" z="0.2"/>'
         '<rgb name="intensity" value="3, 2.5, 2"/></emitter>\n')
CUBE_LIGHT = """    <shape type="cube"><transform name="to_world"><scale x="0.15" y="0.02" z="0.15"/><translate y="0.95"/></transform>
        <emitter type="area"><rgb name="radiance" value="18.387, 13.9873, 6.75357"/></emitter></shape>
"""
DISK_LIGHT = """    <shape type="disk"><transform name="to_world"><scale value="0.25"/><rotate x="1" angle="90"/><translate y="0.98"/></transform>
        <emitter type="area"><rgb name="radiance" value="18.387, 13.9873, 6.75357"/></emitter></shape>
"""
CYLINDER_LIGHT = """    <shape type="cylinder"><point name="p0" x="-0.3" y="0.9" z="0"/><point name="p1" x="0.3" y="0.9" z="0"/><float name="radius" value="0.04"/>
        <emitter type="area"><rgb name="radiance" value="18.387, 13.9873, 6.75357"/></emitter></shape>
"""
BALLS = "".join(f'    <shape type="sphere"><point name="center" x="{-0.8 + 0.2 * (i % 9):.2f}" y="-0.92" '
                f'z="{0.5 - 0.3 * (i // 9):.2f}"/><float name="radius" value="0.08"/><ref id="gray"/></shape>\n'
                for i in range(18))
PATH_INTEGRATOR = """<integrator type='$integrator'>
        <integer name="max_depth" value="$max_depth"/>
    </integrator>"""
DIRECT4 = """<integrator type='direct'>
        <integer name="shading_samples" value="4"/>
    </integrator>"""

# name: (what it changes, edit of the cbox's XML text, or a scene file)
VARIANTS = {
    "cbox": ("the shared cbox itself", lambda s: s),
    "point": ("its area light replaced by a point light", lambda s: s.replace(AREA, "").replace("</scene>", POINT + "</scene>")),
    "point_and_area": ("a point light beside its area light", lambda s: s.replace("</scene>", POINT + "</scene>")),
    "cube_light": ("its light a cube (12 triangles)", lambda s: s.replace(AREA, "").replace("</scene>", CUBE_LIGHT + "</scene>")),
    "disk_light": ("its light an analytic disk", lambda s: s.replace(AREA, "").replace("</scene>", DISK_LIGHT + "</scene>")),
    "cylinder_light": ("its light a cylinder", lambda s: s.replace(AREA, "").replace("</scene>", CYLINDER_LIGHT + "</scene>")),
    "many_spheres": ("18 more spheres on its floor", lambda s: s.replace("</scene>", BALLS + "</scene>")),
    "stratified": ("the stratified sampler", lambda s: s.replace('<sampler type="independent">', '<sampler type="stratified">')),
    "direct4": ("`direct` with shading_samples 4", lambda s: s.replace(PATH_INTEGRATOR, DIRECT4)),
    "spheres": ("spheres alone under the sky", HERE / "scenes" / "spheres.xml"),
}


def scene_file(name: str, out: Path = OUT) -> Path:
    """The variant's scene file (written to `out` from the cbox's, its meshes' paths made
    absolute)."""
    _, edit = VARIANTS[name]
    if isinstance(edit, Path):
        return edit
    text = CBOX.read_text()
    changed = edit(text)
    if name != "cbox" and changed == text:
        raise RuntimeError(f"variant {name}: the edit no longer applies to {CBOX}")
    changed = changed.replace('value="meshes/', f'value="{CBOX.parent / "meshes"}/')
    out.mkdir(parents=True, exist_ok=True)
    path = out / f"{name}.xml"
    path.write_text(changed)
    return path


def survey(name: str, res: int, spp: int, ref_spp: int, repeats: int) -> dict:
    import torch_rbpt as tr
    path = scene_file(name)
    ours = tr.load_file(path, res=res)
    theirs = mitsuba_ref.load_scene(path, res, res)
    cached = OUT / f"{name}_{res}px_{ref_spp}spp_ref.pt"
    if cached.exists():
        ref = torch.load(cached)
    else:
        ref = torch.from_numpy(mitsuba_ref.render(theirs, ref_spp, seed=12345))
        torch.save(ref, cached)
    tr.render(ours, spp=spp, seed=0)
    mitsuba_ref.render(theirs, spp, seed=0)
    t_ours, t_theirs, e_ours, e_theirs = [], [], [], []
    for seed in range(1, repeats + 1):
        start = time.perf_counter()
        image = tr.render(ours, spp=spp, seed=seed)
        t_ours.append(time.perf_counter() - start)
        e_ours.append(rmse(image, ref))
        start = time.perf_counter()
        image = torch.from_numpy(mitsuba_ref.render(theirs, spp, seed=seed))
        t_theirs.append(time.perf_counter() - start)
        e_theirs.append(rmse(image, ref))
    time_ratio = statistics.median(t_ours) / statistics.median(t_theirs)
    error_ratio = statistics.mean(e_ours) / statistics.mean(e_theirs)
    return {"scene": name, "what": VARIANTS[name][0], "res": res, "spp": spp,
            "ours_s": statistics.median(t_ours), "mitsuba_s": statistics.median(t_theirs),
            "ours_rmse": statistics.mean(e_ours), "mitsuba_rmse": statistics.mean(e_theirs),
            "time_ratio": time_ratio, "equal_error_ratio": time_ratio * error_ratio ** 2}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n\n")[0])
    parser.add_argument("--only", default="", help="comma-separated variants (default: all): " + ", ".join(VARIANTS))
    parser.add_argument("--res", type=int, default=128)
    parser.add_argument("--spp", type=int, default=64)
    parser.add_argument("--ref-spp", type=int, default=2048)
    parser.add_argument("--repeats", type=int, default=3)
    parser.add_argument("--quick", action="store_true", help="32 px, 4 spp, reference 64 spp, one repeat")
    args = parser.parse_args()
    if args.quick:
        args.res, args.spp, args.ref_spp, args.repeats = 32, 4, 64, 1
    names = [n for n in args.only.split(",") if n] or list(VARIANTS)
    unknown = [n for n in names if n not in VARIANTS]
    if unknown:
        parser.error(f"unknown variant(s) {', '.join(unknown)}; choose from {', '.join(VARIANTS)}")
    if not mitsuba_ref.available():
        print("Mitsuba 3 is not installed: the survey compares with it, so nothing to do "
              "(pip install mitsuba; see the README's benchmark section).")
        return
    print(f"{cpu_model()}, {datetime.date.today()}, Mitsuba {mitsuba_ref.version()} ({mitsuba_ref.variant()}); "
          f"{args.res} px, {args.spp} spp, reference {args.ref_spp} spp (Mitsuba), median of {args.repeats}")
    print(f"{'scene':15s} {'ours s':>8s} {'Mitsuba s':>9s} {'ours RMSE':>9s} {'Mi RMSE':>9s} "
          f"{'time':>6s} {'eq. error':>9s}  what")
    rows = []
    for name in names:
        r = survey(name, args.res, args.spp, args.ref_spp, args.repeats)
        rows.append({**r, "cpu": cpu_model(), "date": str(datetime.date.today())})
        print(f"{name:15s} {r['ours_s']:8.3f} {r['mitsuba_s']:9.3f} {r['ours_rmse']:9.4f} {r['mitsuba_rmse']:9.4f} "
              f"{r['time_ratio']:6.2f} {r['equal_error_ratio']:9.2f}  {r['what']}", flush=True)
    write_csv(HERE / "results" / ("survey_quick.csv" if args.quick else "survey.csv"), rows)


if __name__ == "__main__":
    main()
