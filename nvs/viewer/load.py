"""python -m nvs.viewer.load ckpt_path=... [load.requests=100]: views per second through the viewer's HTTP endpoint.

Starts the viewer (``python -m nvs.viewer`` with the same overrides, any free port) as its own process and, from
this one, requests views over loopback one at a time, as a drag does: a bounded number of requests on one source
with the pose sweeping the trained range, after warm-up requests. Each latency is the whole round trip (request,
pose step, PNG encoding, JSON, reading the body). Reports the median (views/s = 1000 / median ms), p10/p90, the
server's own model and server times, and the latency of a source switch (encoder + pose step); writes a JSON report
(command, git SHA, date, device, load average before and after) to ``load.out`` (default
``results/viewer/load_<size>.json``, ``load_<size>_threads<n>.json`` with ``threads=<n>``).
"""

from __future__ import annotations

import http.client
import json
import os
import statistics
import time
from pathlib import Path
from urllib.parse import urlencode, urlsplit

import hydra
from hydra.core.hydra_config import HydraConfig
from omegaconf import DictConfig

from nvs.core.atomic import write_json
from nvs.core.errors import UserError
from nvs.core.provenance import header
from nvs.run.cli import exits_cleanly
from nvs.run.compose import CONF_DIR
from nvs.viewer.process import ViewerProcess

def _triangle(i: int, period: int) -> float:
    """0 -> 1 -> 0 over ``period`` steps."""
    x = (i % period) / period
    return 2 * x if x < 0.5 else 2 - 2 * x


def _get(conn: http.client.HTTPConnection, path: str) -> tuple[dict, float]:
    t0 = time.perf_counter()
    conn.request("GET", path)
    response = conn.getresponse()
    body = response.read()
    ms = 1000 * (time.perf_counter() - t0)
    data = json.loads(body)
    if response.status != 200:
        raise UserError(f"GET {path}: {response.status} {data.get('error')}")
    return data, ms


def measure(url: str, requests: int, warmup: int) -> dict:
    """Sequential view requests against a running viewer; latencies in ms (medians and spreads)."""
    if requests < 1 or warmup < 0:
        raise UserError(f"load.requests={requests}, load.warmup={warmup}: need at least one request")
    parts = urlsplit(url)
    conn = http.client.HTTPConnection(parts.hostname, parts.port, timeout=120)  # one keep-alive connection
    info, _ = _get(conn, "/api/info")
    axes = info["controls"]["axes"]
    keys = [s["key"] for s in info["gallery"]]

    def path(key: str, i: int) -> str:
        # axes[0] sweeps its range back and forth (as a horizontal drag); axes[1] moves more slowly.
        values = {ax["name"]: ax["min"] + (ax["max"] - ax["min"]) * _triangle(i, period)
                  for ax, period in zip(axes, (20, 46))}
        return "/api/view?" + urlencode({"source": key, **values})

    for i in range(warmup):
        _get(conn, path(keys[0], i))
    switch = [_get(conn, path(k, 0)) for k in keys[1:6]]  # first views of new sources: encoder + pose step
    views = [_get(conn, path(keys[0], i)) for i in range(requests)]
    conn.close()
    lat = sorted(ms for _, ms in views)
    median = statistics.median(lat)
    return {
        "image_size": info["image_size"], "model": info["model"], "precision": info["precision"],
        "mode": info.get("mode"), "compiled": info.get("compiled"), "pose_gflop": info.get("pose_gflop"),
        "requests": requests, "warmup": warmup,
        "median_ms": median, "p10_ms": lat[int(0.1 * (len(lat) - 1))], "p90_ms": lat[int(0.9 * (len(lat) - 1))],
        "views_per_s": 1000.0 / median,
        "model_median_ms": statistics.median(v["model_ms"] for v, _ in views),
        # CPU time of the server's model thread: with threads=1 all of the model's work, i.e. its latency on an idle
        # core, which a CPU shared with other jobs does not inflate the way it inflates wall-clock times.
        "model_cpu_median_ms": statistics.median(v["model_cpu_ms"] for v, _ in views),
        "server_median_ms": statistics.median(v["server_ms"] for v, _ in views),
        "encoder_reruns": sum(bool(v["encoded"]) for v, _ in views),
        "switch_median_ms": statistics.median(ms for _, ms in switch) if switch else None,
    }


@hydra.main(version_base="1.3", config_path=str(CONF_DIR), config_name="viewer")
@exits_cleanly
def main(cfg: DictConfig) -> None:
    overrides = [o for o in HydraConfig.get().overrides.task if not o.startswith(("load.", "port="))]
    load_before = os.getloadavg()
    # compile=true compiles the pose step before the viewer prints its URL (minutes on a small CPU)
    with ViewerProcess(overrides, timeout_s=900.0 if cfg.compile else 180.0) as url:
        result = measure(url, int(cfg.load.requests), int(cfg.load.warmup))
    report = header("python -m nvs.viewer.load " + " ".join(HydraConfig.get().overrides.task), iso=True,
                    threads=cfg.threads, loadavg_1min_before=load_before[0],
                    loadavg_1min_after=os.getloadavg()[0], **result)
    threads = f"_threads{cfg.threads}" if cfg.threads else ""
    out = Path(cfg.load.out or f"results/viewer/load_{result['image_size']}{threads}.json")
    write_json(out, report)
    print(f"{result['image_size']}²: {result['views_per_s']:.1f} views/s (median {result['median_ms']:.1f} ms end to "
          f"end, p10 {result['p10_ms']:.1f}, p90 {result['p90_ms']:.1f}; model {result['model_median_ms']:.1f} ms, "
          f"model thread CPU {result['model_cpu_median_ms']:.1f} ms; "
          f"source switch {result['switch_median_ms'] or float('nan'):.1f} ms) over {result['requests']} requests")
    print(f"wrote {out}")


if __name__ == "__main__":
    main()
