"""Record Mitsuba 3 BSDF values (eval, pdf, sample) for torch_rbpt's BSDF tests.

    python tests/references/make_bsdf_values.py

Writes ``bsdf_values.json`` next to this file.  Every BSDF is built with ``mi.load_dict``
from the dict stored in the json (``"dict"``), so a test can rebuild the same BSDF.

Setup (scalar_rgb variant, float32): a ``SurfaceInteraction3f`` with an identity shading
frame (``sh_frame = Frame3f(n=(0,0,1))``: s=(1,0,0), t=(0,1,0)), ``n = (0,0,1)``,
``uv = (0.5, 0.5)``, ``si.wi = wi`` (local = world), default ``BSDFContext()`` (radiance
transport, all components).  ``eval`` is the cosine-weighted BSDF value, i.e. Mitsuba's
``bsdf.eval(ctx, si, wo)`` = f(wi, wo) * |cos theta_o| (zero where Mitsuba says so),
``pdf`` is ``bsdf.pdf(ctx, si, wo)`` (solid angle).  ``sample`` entries are
``bsdf.sample(ctx, si, sample1, sample2)``: the BSDFSample (wo, pdf, eta, sampled_type as
flag names and int, sampled_component) and the returned weight (= eval / pdf, for delta
lobes the lobe's weight).
"""

import json
import math
import os
import re

import numpy as np

HERE = os.path.dirname(os.path.abspath(__file__))


def rgb(r, g, b):
    return {"type": "rgb", "value": [r, g, b]}


BSDFS = {
    "diffuse": {"type": "diffuse", "reflectance": rgb(0.2, 0.5, 0.8)},
    "conductor": {"type": "conductor"},
    "twosided_diffuse": {"type": "twosided",
                         "bsdf": {"type": "diffuse", "reflectance": rgb(0.2, 0.5, 0.8)}},
    "dielectric": {"type": "dielectric"},
    "roughplastic": {"type": "roughplastic"},
    "roughplastic_beckmann_a0.05": {
        "type": "roughplastic", "distribution": "beckmann", "alpha": 0.05, "int_ior": 2.0,
        "diffuse_reflectance": rgb(0.07, 0.09, 0.13)},
    "roughplastic_beckmann_a0.3": {
        "type": "roughplastic", "distribution": "beckmann", "alpha": 0.3, "int_ior": 2.0,
        "diffuse_reflectance": rgb(0.07, 0.09, 0.13)},
    "roughplastic_ggx_a0.2": {"type": "roughplastic", "distribution": "ggx", "alpha": 0.2},
}
for dist in ("ggx", "beckmann"):
    for a in (0.1, 0.4):
        BSDFS["roughconductor_%s_a%s" % (dist, a)] = {
            "type": "roughconductor", "distribution": dist, "alpha": a,
            "specular_reflectance": rgb(0.9, 0.6, 0.3)}


def sph(theta_deg, phi_deg):
    t, p = math.radians(theta_deg), math.radians(phi_deg)
    v = np.array([math.sin(t) * math.cos(p), math.sin(t) * math.sin(p), math.cos(t)])
    return v / np.linalg.norm(v)


# (wi, wo) as (theta, phi) in degrees; theta > 90 is below the horizon (inside).
PAIRS_DEG = [
    ((0, 0), (0, 0)),          # normal in, normal out
    ((0, 0), (30, 0)),
    ((30, 0), (30, 180)),      # mirror configuration
    ((45, 30), (45, 210)),     # mirror configuration, other azimuth
    ((60, 0), (20, 90)),
    ((10, 45), (70, 200)),
    ((75, 120), (75, 300)),    # mirror, grazing-ish
    ((85, 0), (85, 180)),      # mirror, near grazing
    ((89, 10), (40, 100)),     # grazing incidence
    ((30, 0), (89.5, 200)),    # grazing exitance
    ((50, 0), (52, 178)),      # near mirror
    ((20, 0), (25, 185)),      # near mirror
    ((5, 0), (5, 180)),        # near normal mirror
    ((45, 0), (45, 90)),
    ((65, 0), (65, 0)),        # retro-reflection
    ((35, 250), (35, 70)),     # mirror
    ((0, 0), (89.9, 0)),
    ((120, 0), (30, 180)),     # wi below the horizon
    ((30, 0), (150, 180)),     # wo below the horizon
    ((30, 0), (150, 0)),       # wo below, straight-through side
    ((135, 0), (135, 180)),    # both below (back side mirror configuration)
    ((160, 40), (110, 250)),   # both below
]

SAMPLE_WI_DEG = [(0, 0), (30, 0), (60, 45), (80, 0), (150, 0)]
SAMPLE_U = [(0.01, (0.3, 0.7)), (0.03, (0.6, 0.2)), (0.5, (0.5, 0.5)), (0.9, (0.8, 0.2)),
            (0.99, (0.05, 0.95))]
SAMPLE_BSDFS = ["dielectric", "conductor", "roughconductor_ggx_a0.4",
                "roughconductor_beckmann_a0.1", "roughplastic", "diffuse"]


RES = 64  # MI_ROUGH_TRANSMITTANCE_RES


def roughplastic_internal(mi, d_orig, make_si):
    """Recover roughplastic's precomputed data from its diffuse-component evaluations.

    Mitsuba 3.9.1 roughplastic (src/bsdfs/roughplastic.cpp) evaluates its diffuse lobe as
        diff / (1 - R_int) * inv_eta_2 * cos_o * t(cos_i) * t(cos_o) / pi
    (nonlinear=true: diff / (1 - diff * R_int)), where t is a 64-entry table of the rough
    dielectric interface's external transmittance at mu_k = max(1e-6, k / 63), linearly
    interpolated (index = min(floor(63 mu), 62)), and R_int its internal diffuse reflectance.
    Neither is exposed by mi.traverse, so we solve for them: with wi = normal and
    wo at cos mu (diffuse component only, ctx.component = 1):
        v(mu) = A t(1) t(mu) mu,  A = diff / (1 - R_int) * inv_eta_2 / pi,
    R_int from the ratio of the nonlinear and linear variants at wi = wo = normal."""
    d = dict(d_orig)
    d["diffuse_reflectance"] = 0.5  # uniform, to make the algebra scalar; tables don't use it
    ctx = mi.BSDFContext()
    ctx.component = 1
    b_lin = mi.load_dict(d)
    b_nl = mi.load_dict(dict(d, nonlinear=True))
    eta = float(np.array(mi.traverse(b_lin)["eta"]).ravel()[0])
    inv_eta_2 = 1.0 / (eta * eta)
    n = [0.0, 0.0, 1.0]

    def ev(b, wi, wo):
        return float(b.eval(ctx, make_si(wi), mi.Vector3f(*wo))[0])

    def dirn(mu):
        return [math.sqrt(max(0.0, 1 - mu * mu)), 0.0, mu]

    r = ev(b_nl, n, n) / ev(b_lin, n, n)
    dif = 0.5
    r_int = (1 - r) / (1 - r * dif)
    A = dif / (1 - r_int) * inv_eta_2 / math.pi
    t1 = math.sqrt(ev(b_lin, n, n) / A)
    table = []
    for k in range(RES):
        mu = k / (RES - 1)
        if k == 0:  # t(c) = t0 + 63 c (t1 - t0) for small c
            c = 1e-3
            tc = ev(b_lin, n, dirn(c)) / (A * t1 * c)
            tk1 = ev(b_lin, n, dirn(1 / (RES - 1))) / (A * t1 / (RES - 1))
            table.append((tc - (RES - 1) * c * tk1) / (1 - (RES - 1) * c))
        else:
            table.append(ev(b_lin, n, dirn(mu)) / (A * t1 * mu))
    # validation: rebuild diffuse evals of the original BSDF at random directions
    b = mi.load_dict(d_orig)
    diff0 = float(b.eval_diffuse_reflectance(make_si([0, 0, 1]))[0])

    def lerp(x):
        x *= RES - 1
        i = min(int(x), RES - 2)
        return table[i] + (table[i + 1] - table[i]) * (x - i)

    rng = np.random.default_rng(0)
    err = 0.0
    for _ in range(200):
        ci, co = rng.uniform(0.01, 1.0, 2)
        wi, wo = dirn(ci), [-math.sqrt(1 - co * co) * 0.6, -math.sqrt(1 - co * co) * 0.8, co]
        wi = [float(np.float32(x)) for x in wi]
        wo = [float(np.float32(x)) for x in wo]
        mit = ev(b, wi, wo)
        ours = diff0 / (1 - r_int) * inv_eta_2 / math.pi * wo[2] * lerp(wi[2]) * lerp(wo[2])
        err = max(err, abs(ours - mit) / abs(mit))
    return dict(
        note=roughplastic_internal.__doc__.strip(),
        eta=eta, inv_eta_2=inv_eta_2, internal_reflectance=r_int,
        external_transmittance_mu=[max(1e-6, k / (RES - 1)) for k in range(RES)],
        external_transmittance=table,
        max_rel_err_rebuilding_200_diffuse_evals=err)


def main():
    import mitsuba as mi
    mi.set_variant("scalar_rgb")

    def make_si(wi):
        si = mi.SurfaceInteraction3f()
        si.p = mi.Point3f(0, 0, 0)
        si.n = mi.Normal3f(0, 0, 1)
        si.sh_frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
        si.uv = mi.Point2f(0.5, 0.5)
        si.wi = mi.Vector3f(*[float(x) for x in wi])
        return si

    def f3(v):
        return [float(v[0]), float(v[1]), float(v[2])]

    def flag_names(t):
        t = int(t)
        return [f.name for f in mi.BSDFFlags.__members__.values()
                if int(f) and (t & int(f)) == int(f) and bin(int(f)).count("1") == 1]

    frame = mi.Frame3f(mi.Vector3f(0, 0, 1))
    assert f3(frame.s) == [1, 0, 0] and f3(frame.t) == [0, 1, 0], (frame.s, frame.t)
    ctx = mi.BSDFContext()
    out = dict(
        description=__doc__.strip(),
        mitsuba_version=mi.__version__, variant=mi.variant(),
        frame=dict(n=[0, 0, 1], s=f3(frame.s), t=f3(frame.t)),
        context="BSDFContext() default: TransportMode.Radiance, all components",
        bsdfs={})
    pairs = [(sph(*a).astype(np.float32), sph(*b).astype(np.float32)) for a, b in PAIRS_DEG]
    for name, d in BSDFS.items():
        bsdf = mi.load_dict(d)
        params = mi.traverse(bsdf)
        entry = dict(dict=d, mitsuba_str=str(bsdf), flags=flag_names(bsdf.flags()),
                     component_count=int(bsdf.component_count()),
                     traverse={k: np.array(params[k]).ravel().tolist() for k in params.keys()},
                     evals=[])
        for (a, b), (wi, wo) in zip(PAIRS_DEG, pairs):
            si = make_si(wi)
            val = bsdf.eval(ctx, si, mi.Vector3f(*[float(x) for x in wo]))
            pdf = bsdf.pdf(ctx, si, mi.Vector3f(*[float(x) for x in wo]))
            entry["evals"].append(dict(wi_deg=list(a), wo_deg=list(b),
                                       wi=[float(x) for x in wi], wo=[float(x) for x in wo],
                                       eval=f3(val), pdf=float(pdf)))
        m = re.search(r"specular_sampling_weight = ([0-9.eE+-]+)", str(bsdf))
        if m:
            entry["internal"] = roughplastic_internal(mi, d, make_si)
            entry["internal"]["specular_sampling_weight_printed"] = float(m.group(1))
            print("   R_int %.6f, t(1) %.6f, t(0) %.6f, max rel err %.2e" % (
                entry["internal"]["internal_reflectance"],
                entry["internal"]["external_transmittance"][-1],
                entry["internal"]["external_transmittance"][0],
                entry["internal"]["max_rel_err_rebuilding_200_diffuse_evals"]))
        if name in SAMPLE_BSDFS:
            entry["samples"] = []
            for a in SAMPLE_WI_DEG:
                wi = sph(*a).astype(np.float32)
                for s1, s2 in SAMPLE_U:
                    si = make_si(wi)
                    bs, w = bsdf.sample(ctx, si, float(s1), mi.Point2f(*s2))
                    entry["samples"].append(dict(
                        wi_deg=list(a), wi=[float(x) for x in wi], sample1=s1,
                        sample2=list(s2), wo=f3(bs.wo), pdf=float(bs.pdf),
                        eta=float(bs.eta), weight=f3(w),
                        sampled_type=int(bs.sampled_type),
                        sampled_type_names=flag_names(bs.sampled_type),
                        sampled_component=int(bs.sampled_component)))
        out["bsdfs"][name] = entry
        print("%-32s %s" % (name, entry["traverse"]))
    path = os.path.join(HERE, "bsdf_values.json")
    # one line per eval/sample record and per list of numbers: small and still readable
    rows = {}
    for e in out["bsdfs"].values():
        for key in ("evals", "samples"):
            tags = []
            for r in e.get(key, []):
                tag = "@@%d@@" % len(rows)
                rows[tag] = json.dumps(r)
                tags.append(tag)
            if key in e:
                e[key] = tags
    text = json.dumps(out, indent=1)
    for tag, row in rows.items():
        text = text.replace('"%s"' % tag, row)
    text = re.sub(r"\[\s*([-0-9.eE+,\s]*?)\s*\]",
                  lambda m: "[" + ", ".join(x.strip() for x in m.group(1).split(",")) + "]"
                  if m.group(1).strip() else "[]", text)
    json.loads(text)  # still valid json
    with open(path, "w") as f:
        f.write(text + "\n")
    print("wrote", path)


if __name__ == "__main__":
    main()
