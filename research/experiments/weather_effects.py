"""The bundled network's car IoU per weather or fault effect at three severities.

Run from the repository root: `python research/experiments/weather_effects.py OUT [--workers 2]`.
For each effect it writes a config (the paper's positions reduced to 5 x 4 on three streets,
one car aligned with the view) whose effect dim takes 0 and the three severities below, runs
`falsify grid` into OUT/<effect>/ (resumable), and prints a Markdown table of mean car IoU per
severity and its ratio to clear, the form of Robo3D's resilience rate.
"""

from __future__ import annotations

import argparse
import subprocess
import sys
from pathlib import Path

import pandas as pd

# effect: (light, moderate, heavy), in the dim's own unit
SEVERITIES: dict[str, tuple[float, float, float]] = {
    "fog": (200.0, 100.0, 50.0),          # m of visibility
    "rain": (10.0, 50.0, 100.0),          # mm/h
    "snow": (1.0, 2.5, 5.0),              # mm/h of water
    "wet_road": (1.0, 2.0, 4.0),          # mm of film
    "beam_loss": (8.0, 16.0, 32.0),       # of 64 lasers
    "crosstalk": (500.0, 2000.0, 8000.0),  # points per scan
    "ego_speed": (30.0, 60.0, 120.0),     # km/h
}

CONFIG = """name = "effect-{effect}"
sensor = "kitti-hdl64e-front"
seed = 0
threshold = 0.65

[dims.car_model]
values = ["sedan"]

[dims.x]
values = [-4.0, -2.0, 0.0, 2.0, 4.0]

[dims.y]
values = [5.0, 9.0, 13.0, 17.0]

[dims.background]
values = [0, 1, 2]

[dims.{effect}]
values = [0.0, {levels}]
"""


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__.splitlines()[0])
    ap.add_argument("out", type=Path)
    ap.add_argument("--workers", type=int, default=2)
    args = ap.parse_args(argv)
    rows = []
    for effect, levels in SEVERITIES.items():
        folder = args.out / effect
        folder.mkdir(parents=True, exist_ok=True)
        config = folder / "config.toml"
        config.write_text(CONFIG.format(effect=effect, levels=", ".join(map(str, levels))))
        run = folder / "run"
        cmd = [sys.executable, "-m", "falsify", "grid", str(config), "--out", str(run),
               "--workers", str(args.workers), "--quiet"]
        if (run / "results.sqlite").exists():
            cmd.append("--resume")
        subprocess.run(cmd, check=True, stdout=subprocess.DEVNULL)
        frame = pd.read_csv(run / "results.csv")
        ok = frame[frame["status"] == "ok"]
        by = ok.groupby(effect)["car_iou"].mean()
        clear = float(by.loc[0.0])
        rows.append((effect, clear, *(float(by.loc[v]) for v in levels), levels))
    print("| effect (light / moderate / heavy) | clear | light | moderate | heavy "
          "| heavy / clear |")
    print("|---|---|---|---|---|---|")
    for effect, clear, a, b, c, levels in rows:
        lv = " / ".join(f"{v:g}" for v in levels)
        print(f"| `{effect}` ({lv}) | {clear:.3f} | {a:.3f} | {b:.3f} | {c:.3f} "
              f"| {c / clear:.2f} |")
    return 0


if __name__ == "__main__":
    sys.exit(main())
