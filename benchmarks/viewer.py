"""What the web viewer costs: a preview frame's time, and training's slow-down while watched.

    python benchmarks/viewer.py                      # the quick start's config and run
    python benchmarks/viewer.py --steps 300 --repeats 5

1. Frame time: a run is trained first if `--run-dir` holds none (the quick start's config,
   `builtin_grid`), then each preview width (64, 128, 256 pixels) and mode (colour, depth,
   colour spread) is rendered from a test camera through `Viewer.render`, as the server does;
   after one warm-up call (compilation), the median of `--repeats` calls is reported.
2. Live viewing: the same config is trained for `--steps` steps twice in fresh run folders,
   once plain and once with the viewer serving the current parameters between steps to a
   headless Chromium page (Debian's `chromium`, driven by playwright, as the browser test
   does); each run's loop time is taken between its first and last step (`fit`'s `on_step`),
   so compilation and the final evaluation are left out. Reported: steps per second of each
   and the fraction by which watching slows training. Skipped, with a note, where Chromium
   or playwright is missing.

Output: `--out`, default `benchmarks/results/viewer_<backend>.json`, with the command and the
machine (`harness.write_json`); a table is printed.
"""

import argparse
import dataclasses
import shutil
import statistics
import tempfile
import time
from pathlib import Path

import harness

import mixnerf_eqx as mx

WIDTHS = (64, 128, 256)
MODES = ("colour", "depth", "colour spread")


def frame_times(run_dir: Path, repeats: int) -> list[dict]:
    run = mx.runs.restore_run(run_dir)
    viewer = mx.Viewer(run.model, run.dataset, port=0, max_width=max(WIDTHS))
    camera = mx.inference.camera_of_view(run.dataset.test, 0)
    rows = []
    try:
        for mode in MODES:
            for width in WIDTHS:
                viewer.render(camera, width, mode)  # compiles once per mode kind
                seconds = []
                for _ in range(repeats):
                    viewer.render(camera, width, mode)
                    seconds.append(viewer.frame_seconds[width])
                height = camera.size(width)[0]
                rows.append(
                    {"mode": mode, "width": width, "height": height, "ms": 1000 * statistics.median(seconds)}
                )
    finally:
        viewer.stop()
    return rows


def loop_seconds(config: mx.Config, dataset, max_width: int | None) -> dict:
    """Trains `config` and times its loop; with `max_width`, watched: the viewer (refining
    frames up to that width) and a browser page."""
    times: list[float] = []
    watched = max_width is not None
    mixture = config.method == "mixnerf"
    viewer = (
        mx.Viewer(None, dataset, port=0, training=True, max_width=max_width, mixture=mixture)
        if watched
        else None
    )
    browser = None

    def on_step(state) -> None:
        if viewer is not None:
            viewer.update(state.model, state.step)
            viewer.wait_while_paused()
        times.append(time.perf_counter())

    try:
        if viewer is not None:
            from playwright.sync_api import sync_playwright  # noqa: PLC0415

            playwright = sync_playwright().start()
            chromium = shutil.which("chromium") or shutil.which("chromium-browser")
            args = ["--use-angle=swiftshader", "--enable-unsafe-swiftshader", "--no-sandbox"]
            browser = playwright.chromium.launch(executable_path=chromium, args=args)
            browser.new_page(viewport={"width": 960, "height": 640}).goto(viewer.url)
        mx.fit(config, dataset=dataset, progress=False, write_renders=False, on_step=on_step)
        frames = 0 if viewer is None else viewer.frames
    finally:
        if browser is not None:
            browser.close()
            playwright.stop()
        if viewer is not None:
            viewer.stop()
    steps = len(times) - 1
    return {"steps": steps, "loop_s": times[-1] - times[0], "frames": frames}


def main() -> None:
    parser = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    parser.add_argument("--config", default="builtin_grid", help="a packaged config or TOML file")
    parser.add_argument("--run-dir", type=Path, default=Path("runs/builtin_grid"), help="the run to view")
    parser.add_argument("--repeats", type=int, default=5, help="timed frames per width and mode")
    parser.add_argument("--steps", type=int, default=300, help="training steps of each live-viewing run")
    parser.add_argument(
        "--live-widths", type=int, nargs="+", default=[128, 256], help="finest preview widths watched live"
    )
    parser.add_argument("--out", default=None, help="result file (default: results/viewer_<backend>.json)")
    args = parser.parse_args()
    config = mx.load_config(args.config)
    if not (args.run_dir / "metrics.json").is_file():
        print(f"training {args.config} into {args.run_dir} first")
        mx.fit(mx.load_config(args.config, [f'train.run_dir="{args.run_dir}"']), progress=False)
    frames = frame_times(args.run_dir, args.repeats)
    harness.print_table(
        ["mode", "width x height", "ms per frame"],
        [[r["mode"], f"{r['width']} x {r['height']}", f"{r['ms']:.0f}"] for r in frames],
    )
    live = None
    if shutil.which("chromium") is None and shutil.which("chromium-browser") is None:
        print("live viewing not measured: Chromium is not installed")
    else:
        dataset = mx.data.load_dataset(config.data)
        runs = {}
        for max_width in (None, *args.live_widths):
            name = "plain" if max_width is None else f"watched_{max_width}"
            with tempfile.TemporaryDirectory() as scratch:
                train = dataclasses.replace(config.train, max_steps=args.steps, run_dir=scratch, eval_every=0)
                runs[name] = loop_seconds(dataclasses.replace(config, train=train), dataset, max_width)
        rate = {name: run["steps"] / run["loop_s"] for name, run in runs.items()}
        slowdown = {name: 1.0 - rate[name] / rate["plain"] for name in runs if name != "plain"}
        live = {**runs, "steps_per_s": rate, "slowdown": slowdown}
        print(f"training {args.steps} steps: {rate['plain']:.1f} steps/s plain")
        for name, fraction in slowdown.items():
            frames_drawn = runs[name]["frames"]
            print(f"  {name}: {rate[name]:.1f} steps/s ({frames_drawn} frames): {100 * fraction:.0f}% slower")
    out = harness.default_out(args.out, "viewer")
    harness.write_json(out, {"frames": frames, "live": live})
    print(f"results: {out}")


if __name__ == "__main__":
    main()
