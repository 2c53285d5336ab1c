"""Fits that predict: each fabric's material as estimated by benchmarks/material_estimation.py (the hanging cloth in a
5 m/s wind, 50 steps), simulated on motions it was not fitted on, against the true fabric.

Motions (16x16 cells, 1 m, float32, frames every 2 steps compared as in the fit):
- wind 10 m/s: the fit's scene (the seed's demo_wind.obj, handles on its top corners) in twice the wind, dt 0.01,
  100 steps;
- drop on a sphere: the flat cloth dropped from 10 cm onto a 0.3 m sphere (repulsion and friction), dt 0.01,
  100 steps;
- shake: the cloth hanging from its two top corners (no wind), the handles shaken 15 cm back and forth across the
  sheet twice a second, dt 0.01, 100 steps;
- stretch: the tensile test (``scenes.stretched_cloth``): the flat sheet held by soft handles on its border, pulled
  to 1.2x along five directions in turn, dt 0.01, 100 steps.
Simulation error: RMS vertex distance to the true fabric's trajectory over the compared frames, per metre of cloth
(the fit's own measure, ``TrajectoryFit.simulation_error``), for the fitted material and for the fit's start (the
mean fabric).

Reads benchmarks/results/material_estimation.json (``--fits PATH``), which must hold the fitted materials; where it
also holds the fits continued on more motions (its ``--multi``: the shake and the stretch, then those and the wind),
their error in the 10 m/s wind and in the drop, the motions here they were not fitted on.

Usage: python benchmarks/prediction.py [--quick] [--out PATH] [--fits PATH] [--steps 100]
       (--quick: 2 fabrics, 10 steps)
"""

from __future__ import annotations

import json
import statistics
from pathlib import Path

import common
import numpy as np
from common import wc
from material_estimation import fitted_material

from warpcloth.tasks import estimation as E
from warpcloth.tasks.scenes import THICKEN, cloth_dropped_on_sphere, hanging_cloth, shaken_cloth, stretched_cloth

DT = 0.01
MOTIONS = ("wind 10 m/s", "drop on a sphere", "shake", "stretch")
UNFITTED_BY_MULTI = ("wind 10 m/s", "drop on a sphere")
"""The motions the fits continued on the shake and the stretch (then with the wind) were not fitted on."""
MULTI_KEY = "fitted_to_three_motions"


def motion_model(motion: str, material: wc.Material) -> wc.Model:
    """The motion's scene with ``material`` (the fit then sets each material it is asked about)."""
    if motion == "wind 10 m/s":
        model = hanging_cloth(material, mesh_path=common.seed_dir() / "meshes" / "demo_wind.obj", requires_grad=False)
        model.wind_velocity.assign(np.array([[10.0, 0.0, 0.0]]))
        return model
    if motion == "drop on a sphere":
        return cloth_dropped_on_sphere(material, requires_grad=False)
    if motion == "shake":
        return shaken_cloth(material, requires_grad=False)
    return stretched_cloth(material, requires_grad=False)


def predict(name: str, fitted: wc.Material, steps: int, multi: wc.Material | None = None) -> dict:
    """Each motion's simulation error of ``fitted`` and of the start; with ``multi`` (the fabric's fit continued on
    the shake and the stretch, then with the wind) also its error on the motions it was not fitted on
    (``UNFITTED_BY_MULTI``)."""
    truth = wc.preset(name, thicken=THICKEN)
    start = E.initial_guess()
    out = {}
    for motion in MOTIONS:
        model = motion_model(motion, truth)
        targets = E.TrajectoryFit.simulate_targets(model, truth, steps=steps, dt=DT)
        fit = E.TrajectoryFit(model, targets, steps=steps, dt=DT)
        out[motion] = {"fitted": fit.simulation_error(fitted), "start": fit.simulation_error(start)}
        if multi is not None and motion in UNFITTED_BY_MULTI:
            out[motion][MULTI_KEY] = fit.simulation_error(multi)
    return out


def main():
    args = common.parse_args(__doc__, fits=str(common.RESULTS_DIR / "material_estimation.json"), steps=100,
                             fabrics=0, quick={"steps": 10, "fabrics": 2})
    fits = json.loads(Path(args.fits).read_text())
    rows = [r for r in fits["per_material"] if "fitted" in r]
    if not rows:
        raise SystemExit(f"{args.fits} holds no fitted materials: rerun benchmarks/material_estimation.py")
    if args.fabrics:
        rows = rows[: args.fabrics]
    multi = {r["material"]: r for r in fits.get("per_material_multi") or []}
    records = []
    for r in rows:
        m = multi.get(r["material"])
        motions = predict(r["material"], fitted_material(r["material"], r["fitted"]), args.steps,
                          None if m is None else fitted_material(r["material"], m["fitted"]))
        records.append({"material": r["material"], "fit_sim_err_pct": r["sim_err_pct"], "motions": motions})
        print(f"{r['material']:20s} fit {r['sim_err_pct']:.3g} %  " + "  ".join(
            f"{m}: {v['fitted']:.3g} % (start {v['start']:.3g} %)" for m, v in motions.items()), flush=True)
    means = {m: {k: statistics.fmean(rec["motions"][m][k] for rec in records)
                 for k in ("fitted", "start", MULTI_KEY) if k in records[0]["motions"][m]}
             for m in MOTIONS}
    means["fit"] = statistics.fmean(rec["fit_sim_err_pct"] for rec in records)
    table = [[rec["material"], rec["fit_sim_err_pct"], *(rec["motions"][m][k] for m in MOTIONS
                                                         for k in ("fitted", "start"))] for rec in records]
    table.append(["mean", means["fit"], *(means[m][k] for m in MOTIONS for k in ("fitted", "start"))])
    common.print_table(["fabric", "fit %", *(f"{m}: {k} %" for m in MOTIONS for k in ("fitted", "start"))], table,
                       ["", ".3g", *[".3g"] * (2 * len(MOTIONS))],
                       title="simulation error against the true fabric on motions not fitted on")
    common.write_result(args, {"steps": args.steps, "dt": DT, "motions": list(MOTIONS), "records": records,
                               "means": means, "fits": fits["meta"]["command"]})


if __name__ == "__main__":
    main()
