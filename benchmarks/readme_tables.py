"""The benchmark figures of README.md and the documentation (docs/**/*.md), rendered from the JSON files the
benchmarks wrote into benchmarks/results/.

Every measured figure in those pages sits in a block

    <!-- results NAME: benchmarks/results/FILE.json [...] -->
    ... (generated: a table, or sentences with the figures) ...
    <!-- end results -->

whose body is ``BLOCKS[NAME]`` applied to those files (one argument per file, in order).
``python benchmarks/readme_tables.py`` rewrites every block of every page from the current results; ``--check`` only
compares and exits 1 on a difference (``tests/test_benchmarks.py`` runs the same check, so a hand-edited figure or a
stale table fails the tests).

Plain JSON and Markdown only: this module imports neither Warp nor warpcloth.
"""

from __future__ import annotations

import argparse
import json
import math
import re
import sys
from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[1]
RESULTS_DIR = REPO_ROOT / "benchmarks" / "results"
README = REPO_ROOT / "README.md"
DOCS = REPO_ROOT / "docs"

BLOCK_RE = re.compile(r"^<!-- results (?P<name>[\w-]+): (?P<files>[^>]*?) -->\n(?P<body>.*?)^<!-- end results -->$",
                      re.S | re.M)


# -- number formats --------------------------------------------------------------------------------------------------
def g(x, n: int = 3) -> str:
    """``x`` to ``n`` significant digits in fixed notation (integers from 10**n up); "–" for None."""
    if x is None or (isinstance(x, float) and not math.isfinite(x)):
        return "–"
    if x == 0:
        return "0"
    a = abs(x)
    if a >= 10 ** (n - 1):
        return f"{x:.0f}"
    digits = n - 1 - math.floor(math.log10(a))
    out = f"{x:.{digits}f}"
    if abs(float(out)) >= 10 ** (n - digits):  # rounding carried into a new digit (9.996 -> 10.00)
        out = f"{x:.{max(digits - 1, 0)}f}"
    return out


def pct(x, n: int = 2) -> str:
    return f"{g(x, n)} %"


def length(x) -> str:
    """A distance [m] in µm, mm or m, two significant digits."""
    if x < 1e-4:
        return f"{g(x * 1e6, 2)} µm"
    if x < 0.1:
        return f"{g(x * 1e3, 2)} mm"
    return f"{g(x, 2)} m"


def sci(x: float) -> str:
    """1e-06 -> 1e-6."""
    text = f"{x:.0e}" if float(f"{x:.0e}") == x else f"{x:g}"
    return re.sub(r"e([-+])0*(\d)", lambda m: "e" + ("-" if m[1] == "-" else "") + m[2], text)


def frac(dt: float) -> str:
    """1/k for a time step of 1/k s."""
    return f"1/{round(1 / dt)}"


def met(ok: bool) -> str:
    return "**met**" if ok else "**not met**"


def table(header: list[str], rows: list[list]) -> str:
    lines = ["| " + " | ".join(header) + " |", "|" + "---|" * len(header)]
    lines += ["| " + " | ".join(str(c) for c in row) + " |" for row in rows]
    return "\n".join(lines)


def provenance(data: dict, what: str = "") -> str:
    """One line: the command, date and load average of the run (from the file's ``meta``)."""
    meta = data.get("meta")
    if not meta:
        return f"Run: {what}(the file predates run metadata)." if what else "Run: (the file predates run metadata)."
    load = meta.get("loadavg_start"), meta.get("loadavg_end")
    load_s = (f"; load average {load[0][0]:g} at the start, {load[1][0]:g} at the end" if all(load) else "")
    env = meta.get("env") or {}
    blas = (", one BLAS thread" if env and set(env.values()) == {"1"}
            else "".join(f", {k}={v}" for k, v in env.items()))
    line = (f"Run: `{meta['command']}`{blas}, {meta['date'][:10]}, {meta['cpu_usable']}/{meta['cpu_count']} CPUs "
            f"({meta['cpu']}), warp {meta['warp']}, {duration(meta['wall_s'])}{load_s}.")
    kept = [key for key in meta.get("kept", ()) if isinstance(data.get(key), dict)]
    if kept:  # records an --only run took over from an earlier one (benchmarks/common.py kept_records)
        line += " " + " ".join(f"`{key}` from the earlier run `{data[key]['kept_meta']['command']}`, "
                               f"{data[key]['kept_meta']['date'][:10]}." for key in kept)
    return line


def duration(seconds: float) -> str:
    return f"{seconds:.0f} s" if seconds < 120 else f"{seconds / 60:.0f} min"


# -- blocks ----------------------------------------------------------------------------------------------------------
def contact(d: dict) -> str:
    rows = [[f"{r['res']}×{r['res']}", g(r["wall_s"]), g(r["mean_step_ms"]), g(r["max_step_s"]),
             *(g(r["phase_ms_per_step"][k]) for k in ("assembly", "proximity", "solve", "integrate", "collision")),
             g(r["cg_iterations_per_step"]), f"{r['pairs_mean']:.0f}"] for r in d["drape"]]
    out = [table(["drape grid", "wall s (100 steps)", "ms/step", "max step s", "assembly", "repulsion + friction",
                  "solve", "integrate", "projection", "CG it/step", "pairs"], rows), ""]
    for i in d["incline"]:
        a = i["acceleration"] if abs(i["acceleration"]) > 1e-9 else 0.0
        travel = g(i["travel_mm"]) if abs(i["travel_mm"]) >= 1e-3 else sci(float(f"{i['travel_mm']:.1e}"))
        out.append(f"Patch on a {i['theta_deg']:.0f}° incline, μ {i['mu']:g}, {i['seconds']:g} s: slid "
                   f"{travel} mm, acceleration {g(a)} m/s² "
                   f"(closed form {g(i['expected_acceleration'])}).")
    for r in d.get("drag", []):
        out.append(f"Patch dragged over a pinned sheet, μ {r['mu']:g}: acceleration {g(r['acceleration'])} m/s² "
                   f"(expected {g(r['expected_acceleration'])}); friction / (μ × load) = "
                   f"{g(r['friction_over_mu_load'])}.")
    out.append(provenance(d))
    return "\n".join(out)


def bvh_update(d: dict) -> str:
    rows = [[name, c["particles"], c["steps"], g(c["rebuild_ms_per_step"]), g(c["refit_ms_per_step"]),
             f"{g(c['speedup'])}×", _diff(c["max_diff_m"])] for name, c in d["cases"].items()]
    return "\n".join([table(["case", "particles", "steps", "rebuilt ms/step", "refitted ms/step", "speed-up",
                             "largest difference [m]"], rows), "", provenance(d)])


def projection_qp(d: dict) -> str:
    rows = [[f"{r['res']}×{r['res']}×{r['layers']}", r["worlds"], r["block_dim"], r["contacts"], r["iterations"],
             g(r["project_ms"]), g(r["adjoint_ms"])] for r in d["records"]]
    return "\n".join([table(["stack (res × res × layers)", "worlds", "block threads", "contacts", "MPRGP iterations",
                             "project ms", "adjoint ms"], rows), "", provenance(d)])


def contact_gradients(d: dict) -> str:
    def num(x):
        return g(x, 4) if abs(x) < 1e5 else sci(float(f"{x:.2g}"))

    def rows(run, label):
        # the stored runs name the landing throw after the tracker's entry that made it
        return [[label, r["point"].removesuffix(" (issue 22)"), g(r["error_pct"]), num(r["grad_norm"]),
                 num(r["tape"]), *(num(fd) for fd in r["central_differences"])] for r in run]

    hs = d["throw"][0]["steps_h"]
    body = rows(d["throw"], "now")
    before = d.get("before")
    if before:
        body += rows(before["throw"], before["label"])
    out = [table(["code", "throw: point", "error %", "‖grad‖", "tape", *(f"CD h={h:g}" for h in hs)], body), ""]
    for label, drape in [("now", d["drape"])] + ([(before["label"], before["drape"])] if before else []):
        o, f = drape["density_only"], drape["all_parameters"]
        out.append(f"Drape fit ({label}; {drape['fabric']}, {drape['steps']} steps onto a box): density alone "
                   f"from +50 %: {pct(o['density_error_pct'])} after {o['evaluations']} evaluations; all 40 "
                   f"parameters from the mean fabric: density {pct(f['parameter_errors_pct']['density_err_pct'])}, "
                   f"simulation error {pct(f['simulation_error_pct'])} (from "
                   f"{pct(f['initial_simulation_error_pct'])}).")
    out.append(provenance(d))
    return "\n".join(out)


def step_time(d: dict) -> str:
    recs = d["records"]
    rows = [[f"{r['res']}×{r['res']}", r["particles"], g(r["forward_ms"]), g(r["taped_forward_ms"]),
             g(r["backward_ms"]), g(r["forward_backward_ms"]), f"{r['cg_iters']:.0f}", f"{r['adjoint_cg_iters']:.0f}"]
            for r in recs]
    out = [table(["grid", "particles", "forward ms", "taped forward ms", "backward ms", "forward+backward ms",
                  "CG it/step", "adjoint CG it/step"], rows), ""]
    by_res = {r["res"]: r for r in recs}
    t = d["targets"]
    targets = []
    if 64 in by_res:
        ms = by_res[64]["forward_ms"]
        targets.append(f"a 64×64 step ≤ {t['step_ms_64']:g} ms ({met(ms <= t['step_ms_64'])}: {g(ms)} ms)")
    if 16 in by_res:
        ms = by_res[16]["forward_backward_ms"]
        targets.append(f"forward+backward ≤ {t['fwd_bwd_ms_16']:g} ms per step at 16×16 "
                       f"({met(ms <= t['fwd_bwd_ms_16'])}: {g(ms)} ms)")
    if targets:
        out.append("Targets from the issue: " + " and ".join(targets) + ".")
    before = d.get("before")
    if before:
        old = {r["res"]: r for r in before["records"]}
        parts = [f"{r['res']}×{r['res']} {g(old[r['res']]['forward_ms'])} → {g(r['forward_ms'])} ms forward, "
                 f"{g(old[r['res']]['forward_backward_ms'])} → {g(r['forward_backward_ms'])} ms forward+backward"
                 for r in recs if r["res"] in old]
        out.append(f"Against {before['label']} (the same benchmark, run just before this one): " + "; ".join(parts)
                   + ".")
    prof = [r for r in recs if r.get("profile")]
    if prof:
        parts = []
        for r in prof:
            f = r["profile"]["forward"]
            cg = f["launch_ms"].get("cg_sequential")
            if cg is not None:
                parts.append(f"{100 * cg / f['total_ms']:.0f} % at {r['res']}×{r['res']}")
        if parts:
            out.append("The CG solve (`cg_sequential`) takes " + ", ".join(parts) + " of the forward step.")
    out.append(provenance(d))
    return "\n".join(out)


def _zone_size(r: dict, key: str) -> str:
    """Mean ± std (max) of a record's zone sizes; none where the fail-safe replaced the projection."""
    if r[key] is None:
        return "fail-safe (below)"
    return f"{r[key]:.0f} ± {r[key + '_std']:.0f} ({r[key + '_max']:.0f})"


def collision_ablation(d: dict) -> str:
    seed = d["seed"]
    rows, phase_rows = [], []
    done = set()
    for r in d["records"]:
        s = seed.get(r["mesh"])
        seed_cell = f"{s['kkt_backward_s']:g} / {s['qr_backward_s']:g}, {s['speedup']:g}" if s else "–"
        done.add(r["mesh"])
        if "error" in r:
            rows.append([r["mesh"].replace("x", "×"), f"raised after {g(r['error_after_s'], 2)} s (below)", "", "", "",
                         "", "", "", seed_cell])
            continue
        rows.append([
            r["mesh"].replace("x", "×"), _zone_size(r, "kkt_size"), _zone_size(r, "qr_size"),
            g(r["kkt_backward_s"]), g(r["qr_backward_s"]), g(r["speedup"]),
            f"{g(r['kkt_backward_zone_s'], 2)} / {g(r['qr_backward_zone_s'], 2)}", g(r["forward_s"], 2), seed_cell])
        if "phases_s" in r:
            p = r["phases_s"]
            phase_rows.append([r["mesh"].replace("x", "×"), *(g(p.get(k, 0.0), 2) for k in (
                "detection", "geometry", "projection", "adjoint", "fail_safe")), g(r["forward_s"], 2)])
    for mesh, s in seed.items():
        if mesh not in done:
            rows.append([mesh.replace("x", "×"), "not run", "", "", "", "", "", "",
                         f"{s['kkt_backward_s']:g} / {s['qr_backward_s']:g}, {s['speedup']:g}"])
    out = [table(["mesh", "KKT size (n+m)", "QR size", "KKT backward s", "QR backward s", "speedup",
                  "per zone: KKT / QR s", "forward s", "seed: KKT / QR s, speedup"], rows), ""]
    if phase_rows:
        out += ["Seconds per step by phase (QR runs):", "",
                table(["mesh", "detection", "normals and weights", "projection (zones, QP)", "adjoint",
                       "fail-safe (rigid zones)", "whole step"], phase_rows), ""]
    device_rows = []
    for r in d["records"]:
        dv = r.get("device")
        if dv is None:
            continue
        if "error" in dv:
            device_rows.append([r["mesh"].replace("x", "×"), f"raised after {g(dv['error_after_s'], 2)} s", "", "", ""])
        else:
            device_rows.append([r["mesh"].replace("x", "×"), g(dv["forward_s"], 2), g(dv["phases_s"]["projection"], 2),
                                g(dv["backward_s"], 2), str(dv["contacts"])])
    if device_rows:
        out += ['With `CollisionOptions(solver="device")` (MPRGP on the dual and a CG adjoint on the active set, Warp '
                "kernels over all contacts, no zones):", "",
                table(["mesh", "whole step s", "projection s", "adjoint s", "contacts"], device_rows), ""]
    # a step the fail-safe resolved has no projection adjoint to time
    measured = [r for r in d["records"] if r["mesh"] in seed and "error" not in r and r["qr_size"] is not None]
    qr = [f"{r['mesh'].replace('x', '×')} {met(r['qr_backward_s'] <= seed[r['mesh']]['qr_backward_s'])} "
          f"({g(r['qr_backward_s'], 2)} s against {g(seed[r['mesh']]['qr_backward_s'], 2)} s)" for r in measured]
    line = "Targets: QR backward at most the seed's: " + "; ".join(qr) + "."
    lim = d.get("target_forward_64_s")
    r64 = next((r for r in d["records"] if r["mesh"] == "64x64"), None)
    if lim and r64 and "error" not in r64:
        line += (f" The 64×64 forward step at most {lim:g} s: {met(r64['forward_s'] <= lim)} "
                 f"({g(r64['forward_s'], 2)} s).")
    failed = [r for r in d["records"] if "error" in r]
    for r in failed:
        line += f" {r['mesh'].replace('x', '×')}: not met, the step raised: “{r['error']}”."
    rounds = sorted({r["rounds"] for r in d["records"] if "error" not in r})
    out.append(line + f" Projection rounds per step: {', '.join(map(str, rounds))}.")
    for r in d["records"]:
        for solver, rec in (("zone", r), ("device", r.get("device") or {})):
            fs = rec.get("fail_safe")
            if rec.get("kept_start_gaps"):
                out.append(f"The {r['mesh'].replace('x', '×')} step with the {solver} solver was resolved by the "
                           "projection's second try, which keeps the start gaps of pairs that start inside the "
                           f"thickness (the first: “{rec['kept_start_gaps'][:120]}”).")
            if fs:
                out.append(f"The {r['mesh'].replace('x', '×')} step with the {solver} solver fell back on rigid impact "
                           f"zones: {fs['zones']} zones of {fs['particles']} particles in all, after {fs['passes']} "
                           f"detection passes (the projection: “{fs['reason'][:120]}”).")
    out.append(provenance(d))
    return "\n".join(out)


CG_ROWS = (("sequential jacobi", "sequential, Jacobi"), ("sequential block_jacobi", "sequential, block Jacobi"),
           ("sequential block_ssor w=1.5", "sequential, block SSOR ω=1.5"),
           ("sequential block_ssor w=1.5 + warm start", "the same, warm-started from the previous step's dv"),
           ("sequential multigrid", "sequential, multigrid (aggregation V-cycle)"),
           ("sequential multigrid + warm start (CPU default)",
            "the same, warm-started from the previous step's dv (CPU default)"),
           ("warp cg diag (library call)", "`warp.optim.linear.cg`, diag"),
           ("warp cg block_jacobi", "`warp.optim.linear.cg`, block Jacobi"),
           ("warp cg multigrid (parallel form)",
            "`warp.optim.linear.cg`, multigrid in parallel form (CUDA default, worlds > 1024 particles)"),
           ("tiled block_jacobi", "tiled, block Jacobi (CUDA default, worlds ≤ 1024 particles; one thread here)"),
           ("tiled multigrid", "tiled, multigrid in parallel form (a V-cycle on each world's block; one thread here)"))


def cg_solvers(d: dict) -> str:
    sizes = [s["res"] for s in d["sizes"]]
    by = {(r["res"], r["solver"]): r for r in d["solves"]}
    header = [f"solver (tol {sci(d['tol'])})"]
    for res in sizes:
        header += [f"{res}² iterations", f"{res}² ms/solve"]
    rows = []
    for key, label in CG_ROWS:
        row = [label]
        for res in sizes:
            r = by.get((res, key))
            row += [r["iters"] if r else "–", g(r["ms_per_solve"]) if r else "–"]
        rows.append(row)
    out = [table(header, rows), ""]
    parts, ssor, mg = [], [], []
    for s in d["sizes"]:
        res = s["res"]
        w, bj = by[(res, "warp cg diag (library call)")], by[(res, "sequential block_jacobi")]
        bs = by[(res, "sequential block_ssor w=1.5")]
        m = by.get((res, "sequential multigrid"))
        if m:
            mg.append(f"{bs['iters']} to {m['iters']} at {res}² (levels of {m['note'].removeprefix('levels ')}; "
                      f"solves {bs['ms_per_solve'] / m['ms_per_solve']:.1f}× faster, "
                      f"{m['ms_per_iter'] / bs['ms_per_iter']:.1f}× the time per iteration)")
        parts.append(f"{g(w['ms_per_iter'], 2)} ms per iteration at {s['n']} particles against "
                     f"{g(bj['ms_per_iter'], 2)} ms per block-Jacobi iteration of the sequential CG (its solve "
                     f"{w['ms_per_solve'] / bj['ms_per_solve']:.0f}× faster)")
        ssor.append(f"from {bj['iters']} to {bs['iters']} at {res}² (solves "
                    f"{bj['ms_per_solve'] / bs['ms_per_solve']:.1f}× faster)")
    out.append("`warp.optim.linear.cg` takes " + "; ".join(parts) + ". Block SSOR cuts iterations against block "
               "Jacobi " + ", ".join(ssor) + ".")
    if mg:
        out.append("The multigrid preconditioner cuts them against block SSOR from " + ", from ".join(mg) + ".")
    parallel = [(by[(s["res"], "sequential multigrid")], by.get((s["res"], "warp cg multigrid (parallel form)")))
                for s in d["sizes"] if (s["res"], "sequential multigrid") in by]
    if parallel and all(p for _, p in parallel):
        out.append("Its parallel form (damped block-Jacobi smoothing, what CUDA runs) takes " + ", ".join(
            f"{p['iters']} against {q['iters']} at {p['res']}²" for q, p in parallel)
            + " (target: within 1.5× of the sequential multigrid's iterations: "
            + met(all(p["iters"] <= 1.5 * q["iters"] for q, p in parallel)) + ").")
    tiled = [(by[(s["res"], "tiled block_jacobi")], by[(s["res"], "tiled multigrid")]) for s in d["sizes"]
             if (s["res"], "tiled multigrid") in by]
    if tiled:
        out.append("On the tiled backend the same V-cycle, on each world's block, cuts block Jacobi's iterations "
                   + ", ".join(f"from {j['iters']} to {m['iters']} at {m['res']}² (solves "
                               f"{j['ms_per_solve'] / m['ms_per_solve']:.2f}× as fast here, where a block is one "
                               "thread)" for j, m in tiled) + ".")
    out.append(provenance(d))
    return "\n".join(out)


def seed_trajectories(d: dict) -> str:
    def contact(r):  # no contact, contact with friction (older files: no "friction" key), contact without
        return ("friction" if r.get("friction", True) else "repulsion") if r.get("contact") else None

    by = {(r["tag"], r["wind_normals"], contact(r)): r for r in d["materials"]}
    tags = list(dict.fromkeys(r["tag"] for r in d["materials"]))
    names = {r["tag"]: r["material"] for r in d["materials"]}
    dt_frame = d["dt"] * d["steps"] / (d["frames"] - 1)
    variants = [("lagged", None, "lagged normals"), ("lagged", "friction", "lagged normals + contact"),
                ("lagged", "repulsion", "lagged normals + contact without friction")]
    variants = [v for v in variants if (tags[0], v[0], v[1]) in by]
    rows = []
    frames = sorted({f for f in (1, 4, 10, d["frames"] - 1) if f < d["frames"]})
    for normals, contact, text in variants:
        for frame in frames:
            rows.append([f"{frame} ({round(frame * dt_frame, 3):g} s), {text}"]
                        + [length(by[(t, normals, contact)]["rms_per_frame"][frame]) for t in tags])
    rows.append(["1 (0.04 s), current normals (default)"]
                + [length(by[(t, "current", None)]["rms_per_frame"][1]) for t in tags])
    out = [table(["frame (t)"] + [names[t] for t in tags], rows), ""]
    for normals, contact, text in variants:
        runs = [by[(t, normals, contact)] for t in tags]
        departs = [r["departs_at_frame"] for r in runs if r["departs_at_frame"] is not None]
        com = [r["com_frame10_error"] for r in runs]
        mean = [r["rms_mean"] for r in runs]
        if departs:
            out.append(f"With the {text} the trajectories first depart by more than 0.1 mm at frames "
                       f"{min(departs)}–{max(departs)}; the centre of mass at frame 10 (0.4 s) is within "
                       f"{length(min(com))}–{length(max(com))} of the seed's; the RMS distance averaged over the "
                       f"{round((d['frames'] - 1) * dt_frame, 3):g} s is {length(min(mean))}–{length(max(mean))}.")
    out.append(provenance(d))
    return "\n".join(out)


def gradient_growth(d: dict) -> str:
    recs = [r for r in d["records"] if r["dtype"] == "float64"]

    def grown(r, key):
        gr = r.get(f"growth_{key}")
        return f"{g(r[f'grad_{key}_norm'])}" + (f" (×{g(gr, 2)})" if gr else "")

    rows = [[f"{r['steps']} steps ({g(r['t_s'], 2)} s)", grown(r, "v0"), grown(r, "density"),
             grown(r, "stretching"), f"{r['f32_vs_f64_v0']:.1e}"] for r in recs]
    out = [table(["horizon", "‖dL/dv0‖", "dL/d(density)", "‖dL/d(stretching)‖",
                  "float32 vs float64 (dL/dv0)"], rows), ""]
    last = recs[-1]
    out.append(f"Norms in float64; growth factors over the previous horizon; horizons beyond {d['tape_max']} steps "
               f"checkpointed. At {last['steps']} steps float32's gradient is within "
               f"{pct(100 * max(last[f'f32_vs_f64_{k}'] for k in ('v0', 'density', 'stretching')))} of float64 "
               "(largest over the three gradients).")
    out.append(provenance(d))
    return "\n".join(out)


def components(d: dict) -> str:
    sizes = list(dict.fromkeys(r["res"] for r in d["rows"]))
    cases = list(dict.fromkeys(r["case"] for r in d["rows"]))
    by = {(r["res"], r["case"]): r for r in d["rows"]}
    header = ["case"]
    for res in sizes:
        header += [f"{res}×{res} ms/step", "vs off", "CG it"]
    rows = []
    for case in cases:
        row = [case]
        for res in sizes:
            r = by[(res, case)]
            vs = r.get("vs_off_pct")
            row += [g(r["ms_per_step"]), "–" if vs is None else ("±0 %" if round(vs) == 0 else f"{vs:+.0f} %"),
                    f"{r['cg_iters']:.0f}"]
        rows.append(row)
    out = [table(header, rows), ""]
    out.append("Phases of one cold step of the free sheet (everything off), through the public API:")
    out.append("")
    out.append(table(["grid", "`sim.assemble` ms", "`sim.linear_solver.solve` ms", "`sim.step` ms", "CG iterations"],
                     [[f"{p['res']}×{p['res']}", g(p["assemble_ms"]), g(p["solve_ms"]), g(p["step_ms"]),
                       p["step_iterations"]] for p in d["phases"]]))
    out.append("")
    out.append(provenance(d))
    return "\n".join(out)


PEER_NAMES = {"warpcloth": "warpcloth", "warpcloth-fast": "warpcloth `fast`", "warpcloth-bdf2": "warpcloth BDF2",
              "warpcloth-captured": "warpcloth, replayed",
              "vbd": "Newton VBD", "style3d": "Newton Style3D", "xpbd": "Newton XPBD",
              "semi_implicit": "Newton SemiImplicit"}


def peers(d: dict) -> str:
    thresholds = d["settings"]["thresholds_pct"]
    first = thresholds[0]
    recs = [r for r in d["records"] if not r.get("is_reference")]
    rows = []
    for e in (e for e in d["equal_error"] if e["threshold_pct"] == first):
        res = e["res"]
        for solver, s in e["per_solver"].items():
            mine = [r for r in recs if r["solver"] == solver and r["res"] == res]
            diverged = [r["dt_label"] for r in mine if r["diverged"]]
            div = f"; {', '.join(diverged)} diverge{'s' if len(diverged) == 1 else ''}" if diverged else ""
            if s["kind"] == "met":
                rows.append([f"{res}×{res}", PEER_NAMES[solver], frac(s["dt"]) + (f" ({div[2:]})" if div else ""),
                             g(s["self_convergence_err"], 2), g(s["ms_per_step"], 2), g(s["sim_s_per_wall_s"], 2)])
            elif s["kind"] == "none met":
                measured = [r for r in mine if r["self_convergence_err"] is not None and not r["diverged"]]
                best = min(measured, key=lambda r: r["self_convergence_err"]) if measured else None
                what = (f"none ({g(best['self_convergence_err'], 2)} % at {best['dt_label']}{div})" if best
                        else "none")
                rows.append([f"{res}×{res}", PEER_NAMES[solver], what, "", g(best["ms_per_step"], 2) if best else "",
                             ""])
            else:
                fastest = [r for r in mine if not r["diverged"]]
                ms = min((r["ms_per_step"] for r in fastest), default=None)
                rows.append([f"{res}×{res}", PEER_NAMES[solver], f"error not measured (over the time budget{div})",
                             "", g(ms, 2) if ms else "", ""])
    out = [table(["grid", "solver", f"fastest dt with error ≤ {first:g} %", "error %", "ms/step",
                  "simulated s per wall s"], rows), ""]
    parts = []
    for th in thresholds:
        ratios = [f"{e['speedup']:.2f}× at {e['res']}²" for e in d["equal_error"]
                  if e["threshold_pct"] == th and e.get("speedup") is not None]
        if ratios:
            parts.append(f"≤ {th:g} %: " + ", ".join(ratios))
    prim = [e for e in d["equal_error"] if e["threshold_pct"] == first and "met" in e]
    if prim:
        target = prim[0]["target"]
        out.append(f"Target: warpcloth ≥ {target:g}× Newton's best at equal error: "
                   f"{met(all(e['met'] for e in prim))} at {first:g} %. warpcloth's simulated seconds per wall "
                   "second over Newton's best (measured, or the optimistic bound of a solver whose error was not "
                   "measured): " + "; ".join(parts) + ".")
    ds = d.get("diffsim")
    if ds and "newton" in ds:
        w, n = ds["warpcloth"], ds["newton"]
        replayed = ""
        if "warpcloth_captured" in ds:
            replayed = (f", {g(ds['warpcloth_captured']['s_per_iter'], 2)} s replayed from a graph "
                        f"(`wc.CapturedRollout`: {ds['speedup_replayed']:.1f}×, {met(ds['speedup_replayed_met'])})")
        out.append(f"Newton's diffsim cloth example ({ds['iters']} iterations): warpcloth {g(w['s_per_iter'], 2)} s "
                   f"per iteration against {g(n['s_per_iter'], 2)} s ({ds['speedup']:.1f}×; target "
                   f"{5:g}×: {met(ds['speedup_met'])}){replayed}; loss after {ds['iters']} iterations "
                   f"{g(w['losses'][-1])} against {g(n['losses'][-1])} (first loss {g(w['losses'][0])} against "
                   f"{g(n['losses'][0])}). "
                   f"warpcloth's dt 1/{round(1 / w['dt'])} moves the 2 s centre of mass by "
                   f"{g(100 * w['com_dt_error_m'], 2)} cm against Newton's dt 1/{round(1 / n['dt'])}.")
    newton = d.get("newton") or (d.get("machine") or {}).get("newton")
    out.append(provenance(d) + (f" Newton {newton}." if newton else ""))
    return "\n".join(out)


def _tradeoff_rows(d: dict, scene: str) -> list[dict]:
    return d["scenes"][scene]


def _row(rows, label):
    return next(r for r in rows if r["label"] == label)


def presets(d: dict) -> str:
    hang, sph = _tradeoff_rows(d, "hanging"), _tradeoff_rows(d, "sphere")
    rows = []
    for name in ("fast", "balanced", "accurate"):
        h, s = _row(hang, f"preset {name}"), _row(sph, f"preset {name}")
        sphere_err = pct(s["err_pct"])
        if abs(s["dt"] - h["dt"]) > 1e-12:
            sphere_err += f" (dt {frac(s['dt'])}, the scene's)"
        rows.append([f"`{name}`", frac(h["dt"]), sci(h["cg_tol"]),
                     f"{pct(h['err_pct'])} / {pct(h['grad_err_pct'])}",
                     f"{g(h['wall_s'], 2)} / {g(h['grad_wall_s'], 2)}",
                     sphere_err, g(s["wall_s"], 2)])
    out = [table(["preset", "max dt", "cg_tol", "hanging sheet: trajectory / gradient error",
                  "wall s per simulated s (fwd / fwd+bwd)", "sphere drape: trajectory error", "wall s per s"],
                 rows), ""]
    out.append(provenance(d))
    return "\n".join(out)


def tradeoff_findings(d: dict) -> str:
    hang, sph = _tradeoff_rows(d, "hanging"), _tradeoff_rows(d, "sphere")

    def fam(rows, family):
        return [r for r in rows if r["family"] == family]

    dts = [r for r in fam(hang, "dt") if "err_pct" in r]
    lines = []
    lines.append("- **The time step is the error.** Implicit Euler is first order: hanging-sheet error "
                 + ", ".join(g(r["err_pct"], 3) for r in dts) + " % at dt " + ", ".join(frac(r["dt"]) for r in dts)
                 + f"; the gradient's error follows ({g(dts[0]['grad_err_pct'], 2)} … "
                 f"{g(dts[-1]['grad_err_pct'], 2)} %).")
    bdf2 = [r for r in fam(hang, "bdf2") if "err_pct" in r]
    if bdf2:
        euler = {r["dt"]: r for r in dts}
        pairs = [(euler[r["dt"]], r) for r in bdf2 if r["dt"] in euler]
        s_euler = {r["dt"]: r for r in fam(sph, "dt") if "err_pct" in r}
        s_pairs = [(s_euler[r["dt"]], r) for r in fam(sph, "bdf2") if "err_pct" in r and r["dt"] in s_euler]
        lines.append("- **BDF2** (`SolverOptions(integrator=\"bdf2\")`) at the same steps: hanging-sheet error "
                     + ", ".join(g(b["err_pct"], 3) for _, b in pairs) + " % (gradient "
                     + ", ".join(g(b["grad_err_pct"], 2) for _, b in pairs) + " %) at dt "
                     + ", ".join(frac(b["dt"]) for _, b in pairs) + ", for "
                     + "–".join(f"{x:.1f}" for x in sorted({min(b["wall_s"] / e["wall_s"] for e, b in pairs),
                                                            max(b["wall_s"] / e["wall_s"] for e, b in pairs)}))
                     + "× backward Euler's forward time. On the sphere, where contact restarts its history, "
                     + ", ".join(f"{g(b['err_pct'], 3)} % against {g(e['err_pct'], 3)} %" for e, b in s_pairs)
                     + " at dt " + ", ".join(frac(b["dt"]) for _, b in s_pairs) + ".")
    tols = [r for r in fam(hang, "cg_tol") if "solve_err_pct" in r]
    tight = max(tols, key=lambda r: -r["cg_tol"])
    loose = [r for r in tols if r["cg_tol"] >= 1e-3]
    sph_dt = {r["label"]: r for r in sph}
    tol_text = ", ".join(f"cg_tol {r['cg_tol']:g} moves the trajectory by {pct(r['solve_err_pct'])} and the gradient "
                         f"by {pct(r['solve_grad_err_pct'])}" for r in loose)
    line = (f"- **The CG tolerance barely matters at a given step**: against the tight solve at the same dt, {tol_text}"
            f", while cutting CG iterations per step from {tight['cg_iters']:.0f} to "
            + "–".join(f"{c:.0f}" for c in sorted({min(r["cg_iters"] for r in loose),
                                                   max(r["cg_iters"] for r in loose)}))
            + f" and the forward time from {g(tight['wall_s'], 2)} to "
            + "–".join(g(w, 2) for w in sorted({min(r["wall_s"] for r in loose), max(r["wall_s"] for r in loose)}))
            + " s per simulated second.")
    s_loose = sph_dt.get("dt 1/400 tol 1e-3")
    s_tight = sph_dt.get("dt 1/400")
    if s_loose and s_tight and "err_pct" in s_loose and "err_pct" in s_tight:
        line += (f" Over many small steps loose solves add up (sphere at dt 1/400: {pct(s_loose['err_pct'])} at "
                 f"1e-3 against {pct(s_tight['err_pct'])} at 1e-8), hence the tighter tolerance of `accurate`.")
    lines.append(line)
    adj_h = [r for r in fam(hang, "adjoint_cg_tol") if "solve_grad_err_pct" in r]
    adj_s = [r for r in fam(sph, "adjoint_cg_tol") if "solve_grad_err_pct" in r]
    if adj_h and adj_s:
        lines.append(f"- **The adjoint tolerance** (`SolverOptions.adjoint_cg_tol`, default = cg_tol) acts on the "
                     f"gradient alone: {adj_h[0]['adjoint_cg_tol']:g} costs {pct(adj_h[0]['solve_grad_err_pct'])} "
                     f"of gradient error on the hanging sheet, {pct(adj_s[0]['solve_grad_err_pct'])} on the sphere.")
    caps = fam(hang, "cg_max_iters")
    capped = [r for r in caps if "err_pct" in r and r["cg_max_iters"] <= 5]
    failed = [r for r in caps if "error" in r]
    if capped or failed:
        line = "- **An iteration cap** under ~10 iterations is a different method, not a cheaper one:"
        if capped:
            line += " " + ", ".join(f"{r['cg_max_iters']} iterations give {pct(r['err_pct'])} error"
                                   for r in capped)
        if failed:
            line += (", " if capped else " ") + ", ".join(str(r["cg_max_iters"]) for r in failed) + \
                    " diverge (`SimulationError`)"
        lines.append(line + ".")
    f64 = [r for r in fam(hang, "dtype") if "solve_err_pct" in r]
    ref = next((r for r in fam(hang, "cg_tol") if abs(r["cg_tol"] - 1e-8) < 1e-20), None)
    if f64 and ref:
        lines.append(f"- **float64** against float32 at cg_tol 1e-8 and the same dt: trajectories "
                     f"{pct(abs(f64[0]['err_pct'] - ref['err_pct']), 2)} apart in error against the reference, "
                     f"{g(f64[0]['wall_s'], 2)} against {g(ref['wall_s'], 2)} s per simulated second (runs vary by "
                     "tens of per cent on this machine).")
    res = [r for r in fam(hang, "res") if "err_pct" in r]
    if res:
        finest = max(fam(hang, "res"), key=lambda r: r["res"])
        base = next((r for r in res if r["res"] == 16), res[0])
        lines.append(f"- **Resolution** (against {finest['res']}×{finest['res']} at the same dt, on the points all "
                     "grids share): " + ", ".join(pct(r["err_pct"]) for r in res if r is not finest)
                     + " at " + ", ".join(f"{r['res']}²" for r in res if r is not finest)
                     + f"; {finest['res']}² is {finest['wall_s'] / base['wall_s']:.0f}× the wall time of "
                     f"{base['res']}².")
    walls = [r["wall_s"] for r in fam(sph, "dt") if "wall_s" in r]
    coarse = [r for r in fam(sph, "dt") if "error" in r]
    thick = [r for r in fam(sph, "thickness") if "err_pct" in r]
    rounds = fam(sph, "collision_rounds")
    line = (f"- **Collisions**: the drape costs {g(min(walls), 2)}–{g(max(walls), 2)} s per simulated second at "
            "16×16 over the steps of the sweep.")
    for r in coarse:
        line += f" At dt {frac(r['dt'])} it stops: {r['error'].split(':')[0]} ({r['error'].split(':')[1].strip()})."
    if thick:
        spread = max(r["err_pct"] for r in thick) - min(r["err_pct"] for r in thick)
        line += (f" Collision thickness {thick[0]['thickness']:g} … {thick[-1]['thickness']:g} m moves the "
                 f"trajectory error by {pct(spread)}.")
    bad = [r for r in rounds if "error" in r]
    good = [r for r in rounds if "err_pct" in r]
    if bad and good:
        same = len({round(r["err_pct"], 6) for r in good}) == 1
        line += (f" {' or '.join(str(r['collision_rounds']) for r in bad)} collision rounds per step are too few "
                 f"(`CollisionError` naming the step and the setting), {good[0]['collision_rounds']} and more give "
                 + ("identical results." if same else "the results above."))
    grads = [r["grad_err_pct"] for r in fam(sph, "dt") if "grad_err_pct" in r]
    if grads:
        line += (f" Gradients through contact do not converge with dt ({g(min(grads), 2)}–{g(max(grads), 2)} % "
                 "against the reference): they are the derivative of the trajectory's piece, which contacts exist "
                 "and which stick changing with dt and with the parameters (by design: see Gradients through "
                 "contact), and the sheet sliding over the sphere amplifies differences between runs.")
    lines.append(line)
    lines.append("")
    lines.append(provenance(d))
    return "\n".join(lines)


def material_estimation(d: dict) -> str:
    keys = ("runtime_s_per_step_iter", "density_err_pct", "stretch_linear_err_pct", "stretch_nonlinear_err_pct",
            "bending_err_pct", "sim_err_pct")
    rows = [[r["material"]] + [g(r[k], 3) for k in keys] for r in d["per_material"]]
    for m in d["means"]:
        rows.append([f"**mean** ({m['optimizer']}, {len(d['per_material'])} fabrics)"] + [g(m[k], 3) for k in keys])
    s = d["seed"]
    rows.append(["seed \"Ours\" (mean of 10, published)"] + [f"{s[k]:g}" for k in keys])
    b = d.get("seed_baseline")
    if b:
        rows.append(["seed Baseline (the mean-fabric start)", "–"] + [f"{b[k]:g}" for k in keys[1:]])
    out = [table(["fabric", "s/step/iter", "density %", "linear str. %", "non-linear str. %", "bending %",
                  "simulation error %"], rows), ""]
    names = {"density_err_pct": "density", "stretch_linear_err_pct": "linear stretching",
             "stretch_nonlinear_err_pct": "non-linear stretching", "bending_err_pct": "bending",
             "sim_err_pct": "simulation error"}
    for m in d["means"]:
        better = [names[k] for k in keys[1:] if m[k] < s[k]]
        worse = [names[k] for k in keys[1:] if m[k] >= s[k]]
        rt = m["runtime_s_per_step_iter"]
        fits = [r for r in d["per_material"] + d.get("per_material_multi", []) if r["optimizer"] == m["optimizer"]]
        worst = max((r["sim_err_pct"] for r in fits), default=None)
        out.append(f"Targets ({m['optimizer']}, means over the fabrics): runtime ≤ 0.02 s/step/iter {met(rt <= 0.02)} "
                   f"({g(rt)}); below the seed's mean error: {', '.join(better) or 'none'}; not below it: "
                   f"{', '.join(worse) or 'none'}"
                   + (f"; no fabric above 3 % simulation error {met(worst <= 3.0)} (largest {g(worst, 3)} %)"
                      if worst is not None else "") + ".")
    cross = d.get("cross_simulator") or []
    if cross:
        each = all(c["sim_err_pct_fitted"] <= 1.0 for c in cross)
        out.append("Fitted to the seed's own trajectories (its C++ code, with self-collision and repulsion), "
                   "simulating as it did (self-collision, repulsion and friction, lagged wind normals): "
                   "simulation error " + "; ".join(
                       f"{c['target']} {g(c['sim_err_pct_start'], 2)} → {g(c['sim_err_pct_fitted'], 2)} % "
                       f"(the true fabric in warpcloth: {g(c['sim_err_pct_true_material'], 2)} %)" for c in cross)
                   + f"; target ≤ 1 % each: {met(each)}"
                   + ".")
    out.append(provenance(d))
    return "\n".join(out)


def motion_control(d: dict) -> str:
    out = []
    seed = d.get("seed", {})
    for key, seed_key, label in (("open_loop", "open-loop", "Open loop (Gauss–Newton)"),
                                 ("mlp_gauss_newton", "mlp", "MLP controller (Gauss–Newton on its weights)"),
                                 ("mlp", "mlp", "MLP controller (Adam)"),
                                 ("mlp_warm", "mlp", "MLP controller warm-started from the open loop (20 simulations "
                                                     "of its Gauss–Newton, then Gauss–Newton on the weights)")):
        r = d.get(key)
        if not r:
            if key != "mlp_warm":  # a record older files do not have
                out.append(f"- {label}: not run." + (" (torch not installed)" if key != "open_loop" else ""))
            continue
        runs = "; ".join(f"{run['start']}: {g(run['error_pct'], 3)} % after {run['simulations']}"
                         + (f" ({len(run['failed_trials'])} trials rejected)" if run["failed_trials"] else "")
                         for run in r["runs"])
        line = (f"- {label}: median **{g(r['error_pct'], 3)} %** after {r['simulations']:g} simulations (to the "
                f"best point; {runs}), {g(r['seconds_per_simulation'], 2)} s per simulation")
        s = seed.get(seed_key)
        if s:
            ok = r["error_pct"] <= s["target_error_pct"] and r["simulations"] <= s["target_simulations"]
            line += (f"; target ≤ {s['target_error_pct']:g} % in ≤ {s['target_simulations']}: {met(ok)}; seed: "
                     f"{s['error_pct']:g} % in {s['simulations']}")
        out.append(line + ".")
    out.append("")
    out.append(provenance(d))
    return "\n".join(out)


def global_search(d: dict) -> str:
    target = d["target"]
    shares = any("capture_share" in r for r in d["optimizers"].values())  # in runs since the capture split

    def share(r):
        return [pct(100 * r["capture_share"], 2)] if shares else []

    rows = []
    for name, r in d["optimizers"].items():
        for run in r["runs"]:
            rows.append([name, run["start"], pct(run["error_pct"], 3), str(run["simulations"]), str(run["iters"]),
                         str(len(run["failed_trials"])), f"{run['seconds']:.0f}"] + share(run))
        rows.append([f"**{name}**", "median", f"**{pct(r['error_pct'], 3)}**", f"{r['simulations']:g}", "", "",
                     f"{r['seconds']:.0f}"] + share(r))
    verdicts = "; ".join(
        f"{name} {met(r['error_pct'] <= target['error_pct'] and r['simulations'] <= target['simulations'])}"
        for name, r in d["optimizers"].items())
    header = ["optimizer", "start", "error", "simulations to the best", "budget", "failed trials", "wall s"]
    header += ["time capturing graphs"] if shares else []
    bound = f", pushes bounded at {d['push_bound']:g} m/s²" if d.get("push_bound") else ""
    return "\n".join([
        table(header, rows), "",
        f"`{d['scene']}`, {d['steps']} steps{bound}; error = |com_T − target| / |com_0 − target|; every simulation "
        f"counted, forward-only ones included. Target: ≤ {target['error_pct']:g} % in ≤ {target['simulations']} "
        f"simulations, median of the starts: {verdicts}.", "", provenance(d) + kept_runs(d["optimizers"])])


def grippers(d: dict) -> str:
    """Gripper control on the fling and fold scenes (benchmarks/grippers.py): every run, medians, the targets."""
    out = []
    for name in ("fling", "fold"):
        p = d.get(name)
        if not p:
            continue
        fling = name == "fling"

        def score(r, fling=fling):
            return pct(100 * r["coverage"], 3) if fling else length(r["mean_distance_m"])

        def to_target(r):
            k = r["to_target_simulations"]
            return "–" if k is None else (f"{k:g} ({g(r['to_target_seconds'], 2)} s)" if "to_target_seconds" in r
                                           and r["to_target_seconds"] is not None else f"{k:g}")

        rows = [["scripted knots", "", score(p["scripted"]), "1", "", ""]]
        if "hand" in p:
            rows.append(["hand-scripted fling", "", score(p["hand"]), "1", "", ""])
        verdicts = []
        for opt, s in p["optimizers"].items():
            for r in s["runs"]:
                rows.append([opt, str(r["seed"]), score(r), str(r["simulations"]), to_target(r), f"{r['seconds']:.0f}"])
            waits = sorted(math.inf if r["to_target_seconds"] is None else r["to_target_seconds"] for r in s["runs"])
            wait = waits[len(waits) // 2] if len(waits) % 2 else 0.5 * (waits[len(waits) // 2 - 1]
                                                                         + waits[len(waits) // 2])
            median = {"to_target_simulations": s["to_target_simulations"],
                      "to_target_seconds": wait if math.isfinite(wait) else None}
            rows.append([f"**{opt}**", "median", f"**{score(s)}**", "", to_target(median), f"{s['seconds']:.0f}"])
            verdicts.append(f"{opt} {met(s['met'])}")
        what = "coverage" if fling else "mean vertex distance"
        t = p["target"]
        goal = (f"coverage ≥ {100 * t['coverage']:g} % in ≤ {t['simulations']} simulations, within "
                f"{t['seconds'] / 60:g} minutes" if fling else
                f"mean vertex distance ≤ {length(t['mean_distance_m'])} in ≤ {t['simulations']} simulations")
        out += [f"**{name}** ({p['steps']} steps; {what} of the best simulation):", "",
                table(["run", "seed", what, "simulations", "to the target (wall)", "wall s"], rows), "",
                f"Target: {goal}, median of the seeds: {'; '.join(verdicts)}.", ""]
    out.append("Every simulation counted; the tasks run uncaptured, so no time goes to capturing graphs. "
               + provenance(d))
    return "\n".join(out)


def kept_runs(records: dict) -> str:
    """Where records an earlier run left (a benchmark's records taken over from it, each with ``kept_meta``) came
    from: " `name`, ... from the earlier run `command`, date, duration." ("" where none was kept)."""
    runs: dict = {}
    for name, r in records.items():
        meta = r.get("kept_meta")
        if meta:
            runs.setdefault((meta["command"], meta["date"][:10], duration(meta["wall_s"])), []).append(name)
    return "".join(f" {', '.join(f'`{n}`' for n in names)} from the earlier run `{command}`, {date}, {wall}."
                   for (command, date, wall), names in runs.items())


def memory(d: dict) -> str:
    rows = [[r["scene"], str(r["steps"]), g(r["full"]["peak_mb"], 3), g(r["checkpointed"]["peak_mb"], 3),
             g(r["ratio"], 2), g(r["full"]["seconds"], 2), g(r["checkpointed"]["seconds"], 2),
             g(r["grad_rel_diff"], 2)] for r in d["records"]]
    ok = all(r["ratio"] <= d["target_ratio"] and r["grad_rel_diff"] <= 1e-6 for r in d["records"])
    parts = [
        "Peak resident memory above the start of one forward + backward (`benchmarks/memory.py`, a fresh process "
        "per scene and mode):", "",
        table(["scene", "steps", "full tape MB", "checkpointed MB", "ratio", "full tape s", "checkpointed s",
               "gradient rel. difference"], rows), "",
        f"Target: checkpointed at most {d['target_ratio']:g} of the full tape's peak with the same "
        f"gradient to 1e-6: {met(ok)}."]
    captured = [r for r in d["records"] if "captured checkpointed" in r]
    if captured:
        rows = [[r["scene"], str(r["steps"]), g(r["captured full"]["peak_mb"], 3),
                 g(r["captured checkpointed"]["peak_mb"], 3), g(r["captured_ratio"], 2),
                 g(r["captured full"]["seconds"], 2), g(r["captured checkpointed"]["seconds"], 2),
                 g(r["captured checkpointed"]["capture_seconds"], 2), g(r["captured_grad_rel_diff"], 2)]
                for r in captured]
        parts += ["", "The same replayed from graphs (`wc.CapturedRollout`, in `segment_steps` segments when "
                  "checkpointed; MB: the peak over the capture and the replays; s: the median of "
                  f"{len(captured[0]['captured full']['replay_seconds'])} replays):", "",
                  table(["scene", "steps", "full tape MB", "checkpointed MB", "ratio", "full tape s",
                         "checkpointed s", "capturing s", "gradient rel. difference"], rows)]
    return "\n".join([*parts, "", provenance(d)])


def prediction(d: dict) -> str:
    motions = d["motions"]
    multi = [m for m in motions if "fitted_to_three_motions" in d["means"][m]]

    def cells(v):
        return [*(f"{pct(v[m]['fitted'])} ({pct(v[m]['start'])})" for m in motions),
                *(pct(v[m]["fitted_to_three_motions"]) for m in multi)]

    rows = [[r["material"], pct(r["fit_sim_err_pct"]), *cells(r["motions"])] for r in d["records"]]
    rows.append(["**mean**", pct(d["means"]["fit"]), *cells(d["means"])])
    header = ["fabric", "fitted motion (wind 5 m/s)", *motions,
              *(f"{m}, fitted to wind, shake and stretch" for m in multi)]
    return "\n".join([table(header, rows), "",
                      "Simulation error of the fitted material against the true fabric; in brackets, the fit's start "
                      "(the mean fabric) on the same motion."
                      + (" Last columns: the fit continued on the shake and the stretch, then on those and the wind "
                         "scene, on the motions it was not fitted on." if multi else ""), "", provenance(d)])


def worlds(d: dict) -> str:
    rows = [[r["scene"], str(r["worlds"]), str(r["particles"]), g(r["forward_world_steps_per_s"], 3),
             f"{r['forward_speedup']:.1f}×", g(r["forward_backward_world_steps_per_s"], 3),
             f"{r['forward_backward_speedup']:.1f}×", f"{r['cg_iterations_per_step']:.1f}"] for r in d["records"]]
    out = ["World-steps per second against the number of worlds in one model (`benchmarks/worlds.py`; forward "
           f"{d['records'][0]['steps']} steps, forward + backward {d['records'][0]['grad_steps']} steps and one "
           "backward pass; speed-up over one world):", "",
           table(["scene", "worlds", "particles", "forward world-steps/s", "speed-up", "fwd+bwd world-steps/s",
                  "speed-up", "CG iterations/step (slowest world)"], rows)]
    target = next((r for r in d["records"] if r["scene"] == "throw" and r["worlds"] == 64), None)
    if target is not None:
        out += ["", f"Target: 64 throw worlds at ≥ {d['target_speedup']:g}× the world-steps per second "
                f"of one world: forward {target['forward_speedup']:.1f}×, forward + backward "
                f"{target['forward_backward_speedup']:.1f}×: {met(target['forward_speedup'] >= d['target_speedup'])}."]
    opt = d.get("optimisation")
    if opt:
        out += ["", f"The throw's open loop (Gauss-Newton, {opt['iters']} simulations a run, {opt['steps']} steps) "
                f"from {opt['starts']} starts, one world at a time against batched (the starts in lockstep, "
                "`optimize_open_loop_starts`: each round's points as one batch of worlds, several points' "
                "Jacobians from one forward and three reverse passes, a lone point's three rows as three worlds; "
                "world simulations count a forward pass shared by three rows once):", "",
                table(["mode", "wall time [s]", "world simulations run", "batches"],
                      [[name, f"{opt[key]['wall_s']:.1f}", str(opt[key]["world_simulations"]),
                        str(opt[key]["batches"])]
                       for name, key in (("one world at a time", "one_world"), ("batched", "batched"))]),
                "", "Each run's result (" + "; ".join(
                    f"{r['start']}: {g(r['error_pct'], 3)} % after {r['simulations']} simulations"
                    for r in opt["runs"]) + f") is the same batched, bitwise: {'yes' if opt['same_result'] else 'no'} "
                f"({opt['batch_retries']} batches run again world by world). Target: "
                f"≥ {d['target_optimisation_speedup']:g}× faster, same result: {opt['speedup']:.2f}×, "
                f"{met(opt['speedup'] >= d['target_optimisation_speedup'] and opt['same_result'])}."]
    fits = d.get("material_estimation")
    if fits:
        out += ["", f"Material estimation of {len(fits['fabrics'])} fabrics (the seed's scene, {fits['steps']} steps, "
                f"L-BFGS from the mean fabric, {fits['iters']} evaluations each, no start scan): one fabric after "
                f"another {fits['one_at_a_time_s']:.1f} s, one batch of {len(fits['fabrics'])} worlds "
                f"(`estimation.estimate_materials`) {fits['batched_s']:.1f} s, {fits['speedup']:.2f}× faster; each "
                f"fit's history and material the same, bitwise: {'yes' if fits['same_result'] else 'no'}."]
    out += ["", provenance(d)]
    return "\n".join(out)


def _diff(x: float) -> str:
    return "0" if x == 0 else f"{x:.0e}"


def graph_step(d: dict) -> str:
    rows = [[f"{r['res']}×{r['res']}", str(r["worlds"]), f"{r['backend']}, {r['preconditioner']}",
             f"{r['cg_iters']:.1f}", f"{r['launches_per_step']:.0f}",
             "–" if r.get("allocs_per_step") is None else f"{r['allocs_per_step']:.0f}", g(r["step_ms"]),
             g(r["step_ms_sync0"]), g(r["captured_ms"]), g(r["world_steps_per_s"]), _diff(r["max_diff"])]
            for r in d["cases"]]
    out = [table(["grid", "worlds", "CG", "CG it/step", "launches/step", "arrays made/step", "step ms",
                  "step ms, sync_every=0", "captured ms", "world-steps/s captured", "captured − uncaptured [m]"],
                 rows)]
    for gr in d["gradients"]:
        out += ["", f"A taped {gr['steps']}-step rollout of the {gr['res']}×{gr['res']} sheet and its backward pass: "
                f"{g(gr['fwd_bwd_s'] * 1e3)} ms, captured {g(gr['fwd_bwd_captured_s'] * 1e3)} ms "
                f"({gr['fwd_bwd_s'] / gr['fwd_bwd_captured_s']:.2f}×); wind gradient captured − uncaptured "
                f"{_diff(gr['max_diff'])}."]
    for key, where in (("throw", "at zero pushes (it falls past everything: no contact)"),
                       ("throw_landing", "at the open loop's best pushes (it lands in the basket)")):
        throw = d.get(key)
        if throw:
            allocs = "–" if throw["allocs_per_step"] is None else f"{throw['allocs_per_step']:.0f}"
            out += ["", f"The seed's throw {where}, {throw['steps']} steps, {throw['particles']} particles, forward + "
                    f"backward (`ThrowTask.evaluate`): a task's first evaluation, uncaptured, "
                    f"{throw['fwd_bwd_s']:.2f} s ({throw['launches_per_step']:.0f} launches and {allocs} arrays made "
                    f"a step); its second, which captures one speculative graph a step, {throw['capturing_s']:.2f} s; "
                    f"later ones, replayed, {throw['replayed_s']:.2f} s, {throw['rerun_steps']} of its steps "
                    f"running uncaptured (target 0.5 s: {met(throw['replayed_s'] <= 0.5)})."]
    drape = d.get("drape")
    if drape:
        out += ["", f"The drape-sphere scene, {drape['steps']} steps, {drape['particles']} particles: "
                f"{drape['drape_ms']:.2f} ms a step uncaptured, {drape['captured_ms']:.2f} ms replayed one graph a "
                f"step ({drape['pair_steps']} steps replayed with their proximity pairs in the graph, "
                f"{drape.get('contact_steps', 0)} with their contacts, {drape['rerun_steps']} run uncaptured; "
                f"captured − uncaptured {_diff(drape['max_diff'])} m); with a loss, forward + backward "
                f"{drape['fwd_bwd_s']:.2f} s uncaptured, "
                f"{drape['fwd_bwd_captured_s']:.2f} s replayed."]
    out += ["", provenance(d)]
    return "\n".join(out)


def jobs(d: dict) -> str:
    counts = d["workers"]
    header = ["jobs", "count"] + [f"{w} worker{'s' if w > 1 else ''} [s]" for w in counts]
    multi = len(counts) > 1
    if multi:
        header += ["speed-up", "same results, bitwise"]
    rows = []
    for r in d["records"]:
        row = [r["set"], str(r["jobs"])] + [f"{r[f'workers_{w}']['wall_s']:.1f}" for w in counts]
        if multi:
            row += [f"{r['speedup']:.2f}×", "yes" if r["same_results"] else "no"]
        rows.append(row)
    out = [f"Wall time of each set of jobs through `run_jobs` (`benchmarks/jobs.py`; Table 2: 10 fabrics, L-BFGS, "
           f"{d['iters']} evaluations, {d['steps']} steps; the throw: the open loop from zero pushes and two random "
           f"starts, {d['control_iters']} simulations each; Ray's start included):", "", table(header, rows)]
    if multi:
        t2 = d["records"][0]
        out += ["", f"Target: Table 2 with 2 workers ≥ {d['target_speedup']:g}× faster than with 1, "
                f"same results: {t2['speedup']:.2f}×, {'same' if t2['same_results'] else 'different'}: "
                f"{met(t2['speedup'] >= d['target_speedup'] and t2['same_results'])}."]
    out += ["", provenance(d)]
    return "\n".join(out)


def integrators(d: dict) -> str:
    """BDF2 against backward Euler: error against dt (with the fitted slope) and the energy a swinging sheet loses."""
    names = {"euler": "backward Euler", "bdf2": "BDF2"}
    scenes = {"free fall": "In free fall, against the exact solution",
              "swinging": "On a sheet swinging in its plane from two soft handles, against BDF2 at a finer step"}
    out = []
    for scene, label in scenes.items():
        parts = []
        for integrator in ("bdf2", "euler"):
            rs = sorted((r for r in d["orders"] if r["scene"] == scene and r["integrator"] == integrator),
                        key=lambda r: -r["dt"])
            if rs:
                parts.append(f"{names[integrator]} {length(rs[0]['err_m'])} … {length(rs[-1]['err_m'])} from dt "
                             f"{frac(rs[0]['dt'])} to {frac(rs[-1]['dt'])}, slope {rs[0]['order']:.2f}")
        if parts:
            out.append(f"- {label}, RMS error at {d['T']:g} s: " + "; ".join(parts) + ".")
    energy = [f"{names[e['integrator']]} {100 * e['end_change']:+.0f} % at dt {frac(e['dt'])}" for e in d["energies"]]
    out.append(f"- Energy in the swinging sheet over {d['energy_T']:g} s, nothing dissipating (the total's change at "
               "the end, in % of the initial kinetic energy): " + ", ".join(energy).replace("-", "−") + ".")
    out += ["", provenance(d)]
    return "\n".join(out)


def recordings(d: dict) -> str:
    """Fits to the seed's target sequences from vertices, point clouds and markers (benchmarks/recordings.py)."""
    kinds = {"vertices": "vertices", "point_clouds": "point clouds", "markers": "markers"}

    def spread(entry, key, runs="chosen", median="median", n=2):  # the median, and the range it is taken over
        values = [r[key] for r in entry[runs]]
        text, low, high = g(entry[median][key], n), g(min(values), n), g(max(values), n)
        return text if low == high else f"{text} ({low}–{high})"

    rows = []
    for s in d["sequences"]:
        for kind, label in kinds.items():
            e = s[kind]
            rows.append([s["target"], label, str(len(e["runs"])), spread(e, "sim_err_pct"),
                         spread(e, "density_err_pct"), spread(e, "stretch_linear_err_pct"),
                         spread(e, "sim_err_pct", "runs", "median_single"),
                         spread(e, "density_err_pct", "runs", "median_single"),
                         g(e["s_per_eval"], 2), g(e["s_per_step_iter"], 2)])
    st = d["settings"]
    out = [table(["sequence", "observation", "fits", "simulation error %", "density %", "linear str. %",
                  "every fit: simulation error %", "density %", "s/eval", "s/step/iter"], rows), ""]
    names = {"point_clouds.sim_err_pct": "point clouds' simulation error", "point_clouds.density_err_pct":
             "point clouds' density error", "markers.sim_err_pct": "markers' simulation error",
             "markers.density_err_pct": "markers' density error",
             "point_clouds.s_per_step_iter": "point-cloud fit's time per step"}
    for key, label in names.items():
        each = [(s["target"], s["targets"][key]) for s in d["sequences"]]
        single = "" if key.endswith("s_per_step_iter") else (
            "; every fit's medians: " + ", ".join(f"{s['target']} {g(s['targets_single'][key]['ratio'], 3)}×"
                                                  for s in d["sequences"]))
        out.append(f"- {label} ≤ {g(each[0][1]['limit'], 2)}× the vertex fit's: {met(d['targets'][key])} ("
                   + ", ".join(f"{t} {g(v['ratio'], 3)}×" for t, v in each) + single + ")")
    def seconds(x):
        return f"{g(x * 1e3, 2)} ms" if x >= 1e-3 else f"{g(x * 1e6, 2)} µs"

    cost = [(s["target"], {k: seconds(c["forward_backward_s_per_frame"]) for k, c in s["loss_cost"].items()})
            for s in d["sequences"]]
    first = d["sequences"][0]
    dropped = len(first["point_clouds"]["runs"][0]["dropped_frames"])
    out += ["", "The losses' cost per frame holding data, forward plus backward: "
            + "; ".join(f"{t}: vertices {c['vertices']}, point clouds {c['point_clouds']}, markers {c['markers']}"
                        for t, c in cost) + ".",
            "", f"{st['optimizer']}, {st['iters']} evaluations of {st['steps']} steps each fit, frames compared every "
            f"{st['frame_stride']} steps; point clouds of {st['points']} points with {g(st['noise_m'] * 1e3, 2)} mm "
            f"noise, {dropped} of the {first['frames']} frames dropped, seen by one depth camera "
            f"(the share of the surface it sees: "
            + ", ".join(f"{s['target']} {g(s['seen_fraction'] * 100, 2)} %" for s in d["sequences"])
            + f"); {st['markers']} markers, {round(st['hidden'] * st['markers'])} of them hidden in each frame, "
            f"drawn at random per frame; each recording ({st['seeds']} seed{'s' if st['seeds'] != 1 else ''} of "
            "point clouds and of markers, the one vertex recording) fitted from each of the starts ("
            + "; ".join(st["starts"]) + ") and the fit of least loss kept: medians over the seeds of these, the "
            "range in parentheses; beside them, medians and ranges over every fit"
            + (f"; {st['workers']} fits at a time, one a core" if st.get("workers", 1) > 1 else "") + ".",
            "", provenance(d)]
    if "parameters" in d:
        out += ["", recording_parameters(d["parameters"])]
    if "start" in d:
        out += ["", recording_start(d["start"])]
    return "\n".join(out)


def recording_start(p: dict) -> str:
    """The start unknown: the fit from point clouds alone against the fit given the true start
    (benchmarks/recordings.py, its ``start`` part, with its own run metadata)."""
    st = p["settings"]
    labels = {"given": "given the start", "alone": "point clouds alone"}

    def each(runs, key, n=2):
        return ", ".join(g(r[key], n) for r in runs)

    def placed(runs):
        return (", ".join(g(r["registration_err_mean_m"] * 100, 2) for r in runs) + " cm; handles "
                + ", ".join("/".join(g(h * 100, 2) for h in r["handle_err_m"]) for r in runs) + " cm; fitted "
                + ", ".join(g(r["fitted_start_err_mean_m"] * 100, 2) for r in runs) + " cm")

    rows = []
    for s in p["sequences"]:
        for kind, label in labels.items():
            e = s[kind]
            rows.append([s["target"], label, g(e["median"]["sim_err_pct"], 2), each(e["runs"], "sim_err_pct"),
                         g(e["median"]["material_sim_err_pct"], 2), g(e["median"]["density_err_pct"], 2),
                         each(e["runs"], "density_err_pct"), "–" if kind == "given" else placed(e["runs"])])
    out = ["The start unknown: the cloth draped and moving at frame 0, its material fitted from point clouds given the "
           "true start, and from the point clouds alone:", "",
           table(["sequence", "fit", "simulation error %", "each seed", "its material from the true start %",
                  "density %", "each seed", "registered start off the true one: mean (each seed); handles; fitted"],
                 rows), ""]
    for key, label in {"sim_err_pct": "simulation error", "density_err_pct": "density error"}.items():
        ts = [(s["target"], s["targets"][key]) for s in p["sequences"]]
        out.append(f"- point clouds alone, {label} ≤ {g(ts[0][1]['limit'], 2)}× the fit given the start: "
                   f"{met(p['targets'][key])} (" + ", ".join(f"{t} {g(v['ratio'], 3)}×" for t, v in ts) + ")")
    out.append("- the fitted material simulated from the true start, point clouds alone over given the start "
               "(outside the target): " + ", ".join(f"{s['target']} {g(s['material_ratio'], 3)}×"
                                                    for s in p["sequences"]))
    out.append("- what the start alone costs: the true material simulated from the registered start, "
               + "; ".join(f"{s['target']} {g(s['truth_from_registered']['truth_sim_err_pct'], 2)} % with the true "
                           f"velocities, {g(s['truth_from_registered']['truth_at_rest_sim_err_pct'], 2)} % at rest "
                           f"(given the start: {g(s['given']['median']['sim_err_pct'], 2)} %)"
                           for s in p["sequences"]))
    handles = ", ".join(str(h) for h in p["sequences"][0]["handles"])
    alone = (f"`registered_start` on the start frame's cloud (the held corners, vertices {handles}, kept where "
             "the scene holds them, the rest deformed onto the points both ways), then `place_start`; "
             "`start_deformation` and `start_deformation_rate` free from zero (the start's shape and velocity in "
             "its 16 smoothest displacements, the held corners fixed), alone for a third of the evaluations, "
             "then with the material, without the start scan; fitted: the fitted start's mean distance from the "
             "true one")
    out += ["", f"From the seed's frame {st['start_frame']}, {st['steps']} steps of {g(st['dt'], 2)} s, frames "
            f"compared every {st['frame_stride']} steps, against the seed's frames from it. Given the start: the "
            f"seed's vertices and velocities (its OBJ `nv` lines) there, the scene's handles. Alone: {alone}. "
            "Simulation error: each fit from its own start; its material from the true start: the fitted material "
            "simulated from the seed's vertices and velocities. "
            f"Point clouds of {st['points']} points with {g(st['noise_m'] * 1e3, 2)} mm noise, "
            f"{g(st['drop'] * 100, 2)} % of the frames dropped, one depth camera; {st['optimizer']}, {st['iters']} "
            f"evaluations a fit from the mean fabric; {st['seeds']} recording seed{'s' if st['seeds'] != 1 else ''}: "
            "medians.", "", provenance({"meta": p.get("meta")})]
    return "\n".join(out)


def recording_parameters(p: dict) -> str:
    """Scene parameters fitted from point clouds with the material known (benchmarks/recordings.py, its
    ``parameters`` part, with its own run metadata)."""
    def value(v, unit="", n=3):
        return (g(v[0], n) if len(v) == 1 else "(" + ", ".join(g(x, n) for x in v) + ")") + unit

    st = p["settings"]
    labels = {"friction": f"cloth dropped on a {g(st['tilt_deg'], 2)}° table: obstacle friction",
              "wind": "hanging cloth: wind velocity",
              "damping": "hanging cloth: Rayleigh damping (α [1/s], β [s])"}
    units = {"friction": "", "wind": " m/s", "damping": ""}
    rows = [[labels[s["scene"]], value(s["truth"], units[s["scene"]]), value(s["start"], units[s["scene"]]),
             "; ".join(value(r["fitted"], n=4) for r in s["runs"]),
             ", ".join(g(r["rel_err_pct"], 2) for r in s["runs"]), g(s["median_rel_err_pct"], 2),
             f"≤ {g(s['limit_pct'], 2)} %: {met(s['met'])}"] for s in p["scenes"]]
    friction = next((s for s in p["scenes"] if s["scene"] == "friction"), None)
    slide = f" (it slides {g(friction['slide_m'] * 100, 2)} cm down)" if friction else ""
    return "\n".join([
        "Scene parameters from point clouds, the material known:", "",
        table(["scene: unknown", "true", "fit's start", "fitted (each seed)", "error % (each seed)",
               "median error %", "target"], rows), "",
        f"A 0.5 m square of 12×12 cells dropped flat from {g(st['drop_height_m'] * 100, 2)} cm onto a plane tilted "
        f"{g(st['tilt_deg'], 2)}°{slide}, and `scenes.hanging_cloth` in the wind (its own 5 m/s for the damping); "
        f"{st['material']}, "
        f"{st['steps']} steps of {g(st['dt'], 2)} s, frames compared every {st['frame_stride']} steps; point clouds of "
        f"{st['points']} points with {g(st['noise_m'] * 1e3, 2)} mm noise, {g(st['drop'] * 100, 2)} % of the frames "
        f"dropped, one depth camera; {st['optimizer']}, {st['iters']} evaluations a fit, the material known; error: "
        f"‖fitted − true‖ / ‖true‖ (the vectors' norms for the wind, the larger of the two coefficients' for the "
        f"damping); {st['seeds']} recording "
        f"seed{'s' if st['seeds'] != 1 else ''}.", "",
        provenance({"meta": p.get("meta")})])


def headline(est: dict, control: dict, ablation: dict) -> str:
    """The README's short table: warpcloth against the seed's published figures on its three experiments."""
    single, multi = est["means"][0], est["means"][-1]
    s = est["seed"]
    rows = [["Material estimation (Table 2): simulation error, mean of 10 fabrics",
             f"{pct(single['sim_err_pct'])} ({pct(multi['sim_err_pct'])} from three motions)",
             f"{s['sim_err_pct']:g} %"],
            ["Material estimation: density error", f"{pct(single['density_err_pct'])} "
             f"({pct(multi['density_err_pct'])} from three motions)", f"{s['density_err_pct']:g} %"],
            ["Material estimation: time per step and evaluation (forward + backward)",
             f"{g(single['runtime_s_per_step_iter'] * 1e3, 2)} ms", f"{s['runtime_s_per_step_iter']:g} s"]]
    for key, seed_key, label in (("open_loop", "open-loop", "Throw into a basket, open loop: error"),
                                 ("mlp_gauss_newton", "mlp", "Throw into a basket, MLP controller: error"),
                                 ("mlp_warm", "mlp", "… the MLP warm-started from the open loop: error")):
        r, sd = control.get(key), control["seed"][seed_key]
        if r:
            worst = max(run["error_pct"] for run in r["runs"])
            rows.append([label, f"{g(r['error_pct'], 3)} % after {r['simulations']:g} simulations (median of "
                         f"{len(r['runs'])} starts; the worst {g(worst, 3)} %)",
                         f"{sd['error_pct']:g} % after {sd['simulations']}"])
    big = ablation["records"][-1]
    seed_big = ablation["seed"].get(big["mesh"])
    if seed_big and big.get("qr_backward_s") is not None:
        rows.append([f"Backward through the collision response, {big['mesh'].replace('x', '×')} (Table 1)",
                     f"{g(big['qr_backward_s'], 2)} s", f"{seed_big['qr_backward_s']:g} s"])
    dates = sorted(d["meta"]["date"][:10] for d in (est, control, ablation))
    return "\n".join([table(["", "warpcloth", "seed (published)"], rows), "",
                      f"A 2-core CPU, runs of {dates[0]} to {dates[-1]}; the commands, the machine and every "
                      "figure: the documentation's results pages."])


BLOCKS = {
    "headline": headline,
    "integrators": integrators,
    "jobs": jobs,
    "graph_step": graph_step,
    "presets": presets,
    "tradeoff_findings": tradeoff_findings,
    "step_time": step_time,
    "collision_ablation": collision_ablation,
    "cg_solvers": cg_solvers,
    "seed_trajectories": seed_trajectories,
    "gradient_growth": gradient_growth,
    "components": components,
    "peers": peers,
    "material_estimation": material_estimation,
    "motion_control": motion_control,
    "global_search": global_search,
    "grippers": grippers,
    "memory": memory,
    "worlds": worlds,
    "prediction": prediction,
    "contact": contact,
    "contact_gradients": contact_gradients,
    "bvh_update": bvh_update,
    "projection_qp": projection_qp,
    "recordings": recordings,
}


# -- the pages -------------------------------------------------------------------------------------------------------
def pages() -> list[Path]:
    """Every page that may hold results blocks: README.md and the documentation's Markdown sources."""
    return [README, *sorted(p for p in DOCS.rglob("*.md") if "_build" not in p.relative_to(DOCS).parts)]


def page_name(path: Path) -> str:
    return str(path.resolve().relative_to(REPO_ROOT)) if path.resolve().is_relative_to(REPO_ROOT) else str(path)


def load(path: str) -> dict:
    p = REPO_ROOT / path
    if not p.resolve().is_relative_to(RESULTS_DIR.resolve()) or p.resolve().parent != RESULTS_DIR.resolve():
        raise ValueError(f"{path}: published figures must come from benchmarks/results/*.json")
    return json.loads(p.read_text())


def blocks(text: str) -> list[re.Match]:
    return list(BLOCK_RE.finditer(text))


def render(name: str, files: str) -> str:
    paths = files.split()
    if name not in BLOCKS:
        raise KeyError(f"unknown results block {name!r} (known: {', '.join(BLOCKS)})")
    if not paths:
        raise ValueError(f"block {name}: no results file named")
    return BLOCKS[name](*(load(p) for p in paths)).rstrip("\n") + "\n"


def update(text: str) -> str:
    def sub(m):
        try:
            body = render(m["name"], m["files"])
        except FileNotFoundError as err:  # not run yet: the block stays as it is
            print(f"warning: block {m['name']} left unchanged: {err}", file=sys.stderr)
            return m[0]
        return f"<!-- results {m['name']}: {m['files']} -->\n{body}<!-- end results -->"

    return BLOCK_RE.sub(sub, text)


def differences(text: str, page: str = "README.md") -> list[str]:
    """One message per block of ``text`` (the page ``page``) whose body differs from its rendering (with the first
    differing line)."""
    out = []
    for m in blocks(text):
        want = render(m["name"], m["files"])
        if m["body"] != want:
            have_lines, want_lines = m["body"].splitlines(), want.splitlines()
            first = next((i for i, (a, b) in enumerate(zip(have_lines, want_lines)) if a != b),
                         min(len(have_lines), len(want_lines)))
            line = text[: m.start()].count("\n") + 2 + first
            out.append(f"{page}:{line}: block {m['name']} differs from {m['files']}:\n"
                       f"  page:      {have_lines[first] if first < len(have_lines) else '(nothing)'}\n"
                       f"  generated: {want_lines[first] if first < len(want_lines) else '(nothing)'}")
    return out


def main():
    p = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    p.add_argument("--check", action="store_true", help="compare only; exit 1 if a block differs")
    p.add_argument("pages", nargs="*", type=Path, help="pages to render (default: README.md and docs/**/*.md)")
    args = p.parse_args()
    diffs, count = [], 0
    for path in args.pages or pages():
        text = path.read_text()
        count += len(blocks(text))
        if args.check:
            diffs += differences(text, page_name(path))
            continue
        new = update(text)
        if new != text:
            path.write_text(new)
            print(f"{len(blocks(text))} results blocks rendered into {page_name(path)}")
    if args.check:
        print("\n".join(diffs) or f"{count} results blocks match their JSON")
        sys.exit(1 if diffs else 0)
    print(f"{count} results blocks in all")


if __name__ == "__main__":
    main()
