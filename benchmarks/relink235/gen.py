"""A seed-duration run (266 stations, the seed's walk) at 1/DIV of the seed's point rate."""
import json
import sys
from dataclasses import replace
from pathlib import Path

sys.path.insert(0, str(Path(__file__).resolve().parents[1]))
import bench_scale as bs


def main():
    folder, div, workers = Path(sys.argv[1]), float(sys.argv[2]), int(sys.argv[3])
    folder.mkdir(parents=True, exist_ok=True)
    config = bs.seed_like_config(235e6)
    config = replace(config, sensor=replace(config.sensor, pulse_rate_hz=config.sensor.pulse_rate_hz / div))
    _, _, info = bs.generate(folder, 235e6 / div, workers, config=config)
    info["div"] = div
    (folder / "gen.json").write_text(json.dumps(info))
    print(info)


if __name__ == "__main__":
    main()
