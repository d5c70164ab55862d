"""`flextrack bench batching`: the gain of the server's dynamic batching (service.batching) for pvnet.

Two `flextrack serve` processes in turn, the same pvnet model and rendered frames: one without
batching, one with `--max-batch B --batch-delay-ms D`. Closed-loop Track streams (the next frame
goes when the answer is back) saturate each; the figure is frames answered per second, latency,
and the mean batch size the server formed (from its /metrics).

With `--untrained`, a freshly initialised network (seeded) is exported instead of a trained one:
the network's cost per frame is the same, but voting and PnP then see random masks, so only the
inference part of the gain is representative.
"""

from __future__ import annotations

import argparse
import json
import re
import tempfile
import time
import urllib.request
from pathlib import Path

from flextrack import assets
from flextrack.loadtest import report, runner, servers, workload
from flextrack.provenance import of_args

DEFAULT_MODEL = assets.pvnet_model_path()


def add_arguments(parser: argparse.ArgumentParser) -> None:
    parser.add_argument("--model", type=Path, default=DEFAULT_MODEL, help="PVNet ONNX model of the default object")
    parser.add_argument("--untrained", action="store_true", help="export a seeded untrained network instead")
    parser.add_argument("--max-batch", type=int, default=8, help="the server's --max-batch in the batched run (default: %(default)s)")
    parser.add_argument("--batch-delay-ms", type=float, default=5.0,
                        help="the server's --batch-delay-ms in the batched run (default: %(default)g)")
    parser.add_argument("--clients", type=int, default=8, help="closed-loop Track streams")
    parser.add_argument("--workers", type=int, default=8, help="estimator threads of the unbatched server")
    parser.add_argument("--frames", type=int, default=8, help="rendered frames, cycled")
    parser.add_argument("--duration", type=float, default=8.0, help="seconds measured per run (default: %(default)g)")
    parser.add_argument("--payload-kb", type=float, default=100.0, help="request size, kB (default: %(default)g)")
    parser.add_argument("--out", type=Path, default=Path("out/bench_batching"),
                        help="folder for batching.json and the server's log (default: %(default)s)")


def _untrained_model(path: Path, keypoints) -> Path:
    import torch

    from flextrack.training.export_onnx import export
    from flextrack.training.pvnet_model import PvnetNet

    torch.manual_seed(0)
    return export(PvnetNet(num_keypoints=len(keypoints)), path, keypoints)


def _mean_batch(metrics_address: str) -> float:
    text = urllib.request.urlopen(f"http://{metrics_address}/metrics", timeout=5).read().decode()
    total = sum(float(v) for v in re.findall(r"^flextrack_batch_size_sum\{[^}]*\} (\S+)$", text, re.MULTILINE))
    count = sum(float(v) for v in re.findall(r"^flextrack_batch_size_count\{[^}]*\} (\S+)$", text, re.MULTILINE))
    return total / count if count else 1.0


def run(args: argparse.Namespace) -> int:
    from estimators.objects import load_object
    from flextrack.training.evaluate import rendered_frames

    args.out.mkdir(parents=True, exist_ok=True)
    with tempfile.TemporaryDirectory() as tmp:
        model = args.model
        if args.untrained:
            keypoints = load_object("default", assets.default_object_model()).keypoints
            model = _untrained_model(Path(tmp) / "pvnet_untrained.onnx", keypoints)
        elif not model.is_file():
            print(f"bench batching: model {model} not found (train one with `flextrack train pvnet`, or --untrained)")
            return 2
        config = Path(tmp) / "batching.toml"
        config.write_text(f'[objects.default]\nmodel = "{assets.default_object_model()}"\n\n[[estimators]]\nname = "pvnet"\n'
                          f'kind = "pvnet"\nobjects = ["default"]\nmodel = "{model}"\n')
        frames = list(rendered_frames(assets.default_object_model(), args.frames, seed=7, scenes=1))
        work = workload.from_images([f[1] for f in frames], frames[0][2], args.payload_kb, "pvnet", "default")
        rows = []
        for label, extra in (("off", ["--max-batch", "1"]),
                             (f"max {args.max_batch}, {args.batch_delay_ms:g} ms",
                              ["--max-batch", str(args.max_batch), "--batch-delay-ms", str(args.batch_delay_ms)])):
            metrics_port = servers.free_port()
            server = servers.start_serve(["--config", str(config), "--workers", str(args.workers), "--metrics-port",
                                          str(metrics_port), "--log-level", "WARNING", *extra], f"batching {label}",
                                         log_path=args.out / "server.log")
            try:
                spec = runner.LoadSpec((server.address,), args.clients, fps=1000.0, duration_s=args.duration,
                                       warmup_s=2.0)
                summary = report.summarize(runner.run(spec, work))
                mean_batch = _mean_batch(f"127.0.0.1:{metrics_port}")
            finally:
                server.stop()
            lat = summary["latency_all"]
            rows.append({"batching": label, "frames_per_s": summary["throughput_fps"], "p50_ms": lat["p50_ms"],
                         "p99_ms": lat["p99_ms"], "mean_batch": mean_batch, "outcomes": summary["outcomes"]})
            print(f"batching {label:<16}: {summary['throughput_fps']:6.1f} frames/s, p50 {lat['p50_ms']:.0f} ms, "
                  f"p99 {lat['p99_ms']:.0f} ms, mean batch {mean_batch:.2f}", flush=True)
    gain = rows[1]["frames_per_s"] / rows[0]["frames_per_s"] if rows[0]["frames_per_s"] else float("nan")
    print(f"dynamic batching gain: x{gain:.2f} frames/s ({args.clients} closed-loop streams, "
          f"{'untrained' if args.untrained else 'trained'} model)")
    (args.out / "batching.json").write_text(json.dumps(
        {"date_utc": time.strftime("%Y-%m-%d %H:%M UTC", time.gmtime()), "model": str(model) if not args.untrained
         else "untrained (seeded)", "clients": args.clients, "rows": rows, "gain": gain,
         "provenance": of_args(args, command="flextrack bench batching")}, indent=2))
    return 0
