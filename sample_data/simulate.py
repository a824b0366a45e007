"""Generate a simulated kinematic run with ground truth (see sample_data/README.md).

    python sample_data/simulate.py --out sample_data                  # the committed sample
    python sample_data/simulate.py --out /tmp/other --layout central_corridor --building-seed 7 \
        --size-m 30 14 3.2 --n-rooms 5 --seed 11 --duration-s 400 --utm

Deterministic: the same arguments give the same files.
"""

from __future__ import annotations

import argparse
import dataclasses
import sys
import time
from pathlib import Path

from kinreg.simulation.files import static_targets_csv, write_run
from kinreg.simulation.run import SimulationConfig, simulate_run
from kinreg.simulation.scene import BuildingLayout

UTM_ORIGIN = (500000.0, 5400000.0, 0.0)


def parse_args(argv: list[str] | None = None) -> argparse.Namespace:
    d = SimulationConfig()
    p = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    p.add_argument("--out", type=Path, required=True, help="output folder (created if missing)")
    p.add_argument("--seed", type=int, default=d.seed, help="seed of walk, drift, noise, static scans")
    p.add_argument("--duration-s", type=float, default=d.duration_s)
    p.add_argument("--t0-s", type=float, default=d.t0_s, help="time of the first trajectory row (GPS-like)")
    p.add_argument("--block-s", type=float, default=d.block_s, help="seconds of scanning per generated block")
    b = p.add_argument_group("building")
    b.add_argument("--layout", choices=[x.value for x in BuildingLayout], default=d.building.layout.value)
    b.add_argument("--building-seed", type=int, default=d.building.seed)
    b.add_argument("--size-m", type=float, nargs=3, default=d.building.size_m, metavar=("X", "Y", "H"))
    b.add_argument("--n-rooms", type=int, default=d.building.n_rooms)
    s = p.add_argument_group("sensor")
    s.add_argument("--pulse-rate-hz", type=float, default=d.sensor.pulse_rate_hz)
    s.add_argument("--line-rate-hz", type=float, default=d.sensor.line_rate_hz)
    s.add_argument("--n-beams", type=int, default=d.sensor.n_beams)
    s.add_argument("--head-rate-hz", type=float, default=d.sensor.head_rate_hz)
    s.add_argument("--range-sigma-m", type=float, default=d.sensor.range_sigma_m)
    s.add_argument("--angle-sigma-deg", type=float, default=d.sensor.angle_sigma_deg)
    s.add_argument("--max-range-m", type=float, default=d.sensor.max_range_m)
    r = p.add_argument_group("drift")
    r.add_argument("--drift-pos-m-at-300s", type=float, default=d.drift.drift_pos_m_at_300s)
    r.add_argument("--drift-rot-deg-at-300s", type=float, default=d.drift.drift_rot_deg_at_300s)
    t = p.add_argument_group("static scans")
    t.add_argument("--n-static", type=int, default=d.static.n_scans)
    t.add_argument("--static-step-deg", type=float, default=d.static.angle_step_deg)
    t.add_argument("--targets", type=int, default=0, metavar="N",
                   help="also write N targets per static scan as targets.csv (surveyed, kinreg's --control "
                        "format with station,sx,sy,sz) and targets_truth.csv (true coordinates)")
    o = p.add_argument_group("coordinates")
    o.add_argument("--origin", type=float, nargs=3, default=d.origin_xyz, metavar=("E", "N", "H"),
                   help="offset added to every object-frame output")
    o.add_argument("--utm", action="store_true",
                   help=f"shortcut for --origin {' '.join(map(str, UTM_ORIGIN))}")
    return p.parse_args(argv)


def config_from_args(a: argparse.Namespace) -> SimulationConfig:
    d = SimulationConfig()
    return SimulationConfig(
        seed=a.seed,
        duration_s=a.duration_s,
        t0_s=a.t0_s,
        block_s=a.block_s,
        building=dataclasses.replace(d.building, layout=BuildingLayout(a.layout), seed=a.building_seed,
                                     size_m=tuple(a.size_m), n_rooms=a.n_rooms),
        sensor=dataclasses.replace(d.sensor, pulse_rate_hz=a.pulse_rate_hz, line_rate_hz=a.line_rate_hz,
                                   n_beams=a.n_beams, head_rate_hz=a.head_rate_hz,
                                   range_sigma_m=a.range_sigma_m, angle_sigma_deg=a.angle_sigma_deg,
                                   max_range_m=a.max_range_m),
        drift=dataclasses.replace(d.drift, drift_pos_m_at_300s=a.drift_pos_m_at_300s,
                                  drift_rot_deg_at_300s=a.drift_rot_deg_at_300s),
        static=dataclasses.replace(d.static, n_scans=a.n_static, angle_step_deg=a.static_step_deg),
        origin_xyz=UTM_ORIGIN if a.utm else tuple(a.origin),
    )


class _PrintProgress:
    def start(self, stage: str, total: float | None = None, unit: str = "") -> None:
        self.stage, self.total, self.done = stage, total, 0.0

    def advance(self, amount: float = 1.0) -> None:
        self.done += amount
        print(f"\r{self.stage}: {self.done:.0f}/{self.total:.0f}", end="", file=sys.stderr, flush=True)

    def finish(self) -> None:
        print(file=sys.stderr)


def main(argv: list[str] | None = None) -> int:
    args = parse_args(argv)
    cfg = config_from_args(args)
    t_start = time.perf_counter()
    run = simulate_run(cfg)
    files = write_run(run, args.out, progress=_PrintProgress())
    if args.targets > 0:
        for name, noise in (("targets.csv", True), ("targets_truth.csv", False)):
            files.files[name] = args.out / name
            files.files[name].write_text(static_targets_csv(run, args.targets, noise=noise))
    elapsed = time.perf_counter() - t_start
    dp, da = run.drift_at_end()
    print(f"scene {run.scene.name}: {len(run.scene.patches)} patches, {len(run.scene.planes())} planes")
    print(f"walk {run.truth.path_length_m():.1f} m in {cfg.duration_s:.0f} s, "
          f"{len(run.truth)} trajectory rows")
    print(f"cloud {files.n_points:,} points; static {', '.join(f'{n:,}' for n in files.n_static_points)}")
    print(f"drift at end: {dp * 1e3:.1f} mm, {da:.3f} deg")
    print(f"{elapsed:.1f} s, {files.n_points / elapsed:,.0f} points/s end to end")
    for name, path in files.files.items():
        print(f"  {name:22s} {path.stat().st_size / 1e6:8.2f} MB")
    return 0


if __name__ == "__main__":
    raise SystemExit(main())
