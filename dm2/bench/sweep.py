"""Monte Carlo sweeps over seeds and fault magnitudes on Dask distributed.

:func:`sweep_cases` expands a base scenario into one case per (size, seed): the size is written
into one field of one fault (``faults[i].<param>``), the seed into ``seed``; with ``controls``,
one fault-free control per seed follows (every fault removed, all else the same), so the false
tracks and false real-time alarms of the same settings over the same seeds stand beside the
detection probability. :func:`run_sweep`
maps a case function over them on a Dask client: a :class:`distributed.LocalCluster` of worker
processes (one thread each, so each process holds one physics engine) by default, or the
scheduler at ``scheduler_address``. :func:`summarize_sweep` turns the case results into the
detection probability per size and the smallest reliably detected size; the result depends
only on the cases, never on the order in which workers finish.
"""

from __future__ import annotations

import contextlib
import copy
import logging
from collections.abc import Callable, Sequence
from pathlib import Path

import numpy as np

log = logging.getLogger(__name__)

RELIABLE_PROBABILITY = 0.9


def sweep_cases(base: dict, sizes: Sequence[float], seeds: Sequence[int],
                param: str = "height_mm", fault_index: int = 0,
                controls: bool = False) -> list[dict]:
    """One scenario dict per (size, seed), sizes outer, seeds inner; with ``controls``, then
    one fault-free control per seed (``size`` None, ``control`` True: the base without its
    faults, at the same settings and seed).

    Raises
    ------
    ValueError : the base scenario has no fault ``fault_index``, or sizes/seeds are empty
    """
    faults = base.get("faults") or []
    if not 0 <= fault_index < len(faults):
        raise ValueError(f"sweep: the base scenario has no faults[{fault_index}] to vary "
                         f"({len(faults)} fault(s))")
    if not sizes or not seeds:
        raise ValueError("sweep: give at least one size and one seed")
    cases = []
    for size in sizes:
        for seed in seeds:
            sc = copy.deepcopy(base)
            sc["faults"][fault_index][param] = float(size)
            sc["seed"] = int(seed)
            sc["name"] = f"{base.get('name', 'sweep')}_{param}{size:g}_seed{seed}"
            cases.append({"size": float(size), "seed": int(seed), "scenario": sc})
    for seed in seeds if controls else ():
        sc = copy.deepcopy(base)
        sc["faults"] = []
        sc["seed"] = int(seed)
        sc["name"] = f"{base.get('name', 'sweep')}_control_seed{seed}"
        cases.append({"size": None, "seed": int(seed), "control": True, "scenario": sc})
    return cases


def run_sweep(cases: list[dict], case_fn: Callable[[dict, str], dict], *,
              scheduler_address: str | None = None, n_workers: int = 2,
              threads_per_worker: int = 1, progress: Callable[[int, int], None] | None = None,
              client=None) -> list[dict]:
    """Run ``case_fn(scenario_dict, source)`` for every case on Dask; results in case order.

    ``case_fn`` must be importable by the workers (a module-level function). An open
    ``client`` is used as it is (and left open); otherwise one is made for the call.
    """
    from distributed import Client, LocalCluster

    if client is not None:
        return _collect(client, cases, case_fn, progress)
    cluster = None
    with contextlib.ExitStack() as quiet:
        if scheduler_address is None:
            # the local cluster's life cycle (and the comm tracebacks its shutdown logs at
            # INFO) is no news to the user; its warnings and errors still show
            quiet.enter_context(_logger_level("distributed", logging.WARNING))
            cluster = LocalCluster(n_workers=n_workers, threads_per_worker=threads_per_worker,
                                   processes=True, dashboard_address=None,
                                   silence_logs=logging.ERROR)
            client = Client(cluster)
        else:
            client = Client(scheduler_address)
        try:
            return _collect(client, cases, case_fn, progress)
        finally:
            client.close()
            if cluster is not None:
                cluster.close()


@contextlib.contextmanager
def _logger_level(name: str, level: int):
    """Raise logger ``name`` to at least ``level`` for the block (records below it are not
    even created), then restore it."""
    logger = logging.getLogger(name)
    old = logger.level
    logger.setLevel(max(level, logger.getEffectiveLevel()))
    try:
        yield
    finally:
        logger.setLevel(old)


def _collect(client, cases, case_fn, progress) -> list[dict]:
    from distributed import as_completed

    futures = [client.submit(case_fn, c["scenario"], c["scenario"]["name"], pure=False)
               for c in cases]
    index = {f.key: i for i, f in enumerate(futures)}
    results: list[dict | None] = [None] * len(cases)
    for done, fut in enumerate(as_completed(futures), start=1):
        results[index[fut.key]] = fut.result()
        if progress is not None:
            progress(done, len(cases))
    return [{"size": c["size"], "seed": c["seed"], **({"control": True} if c.get("control")
                                                      else {}), **r}
            for c, r in zip(cases, results, strict=True)]


def summarize_sweep(results: list[dict], reliable: float = RELIABLE_PROBABILITY) -> dict:
    """Detection probability per size and the smallest size detected reliably from there up.

    A case counts as detected when the fault was found with the right sign by any track
    (``probability``) or by a global over/underbuild track (``probability_global``). The smallest
    reliable size is the smallest size at and above which every size's probability is at
    least ``reliable`` (None if even the largest misses it). The fault-free controls (results
    with ``control``) are summed apart: ``control`` ``{"n", "false_tracks", "drift_tracks",
    "realtime_false_alarms"}`` (None without controls); each size row also carries its own
    ``realtime_false_alarms`` and ``drift_tracks``.
    """
    controls = [r for r in results if r.get("control")]
    results = [r for r in results if not r.get("control")]
    sizes = sorted({r["size"] for r in results})
    by_size = []
    for s in sizes:
        rows = [r for r in results if r["size"] == s]
        hits = [bool(r.get("detected") and r.get("sign_ok")) for r in rows]
        hits_global = [bool(r.get("detected_global") and r.get("sign_ok")) for r in rows]
        peaks = [r["peak_height_mm"] for r in rows if r.get("peak_height_mm") is not None]
        delays = [r["onset_delay_layers"] for r in rows if r.get("onset_delay_layers") is not None]
        by_size.append({"size": s, "n": len(rows), "detected": int(sum(hits)),
                        "probability": float(np.mean(hits)),
                        "probability_global": float(np.mean(hits_global)),
                        "mean_peak_height_mm": float(np.mean(peaks)) if peaks else None,
                        "mean_onset_delay_layers": float(np.mean(delays)) if delays else None,
                        "false_positive_tracks": int(sum(r.get("false_positive_tracks", 0)
                                                         for r in rows)),
                        "drift_tracks": int(sum(r.get("drift_tracks", 0) for r in rows)),
                        "realtime_false_alarms": int(sum(r.get("realtime_false_alarms", 0)
                                                         for r in rows))})
    smallest = None
    for row in reversed(by_size):
        if row["probability"] < reliable:
            break
        smallest = row["size"]
    control = None if not controls else {
        "n": len(controls), "seeds": sorted(int(r["seed"]) for r in controls),
        "false_tracks": int(sum(r.get("false_positive_tracks", 0) for r in controls)),
        "drift_tracks": int(sum(r.get("drift_tracks", 0) for r in controls)),
        "realtime_false_alarms": int(sum(r.get("realtime_false_alarms", 0) for r in controls))}
    return {"reliable_probability": reliable, "by_size": by_size,
            "smallest_reliable_size": smallest, "control": control}


def plot_sweep(path: str | Path, summary: dict, param: str, title: str = "") -> Path:
    """Detection probability against size (PNG), the reliability level dashed."""
    import matplotlib

    matplotlib.use("Agg")
    import matplotlib.pyplot as plt

    rows = summary["by_size"]
    fig, ax = plt.subplots(figsize=(6, 4))
    ax.plot([r["size"] for r in rows], [r["probability"] for r in rows], "o-",
            label="detected (any track)")
    ax.plot([r["size"] for r in rows], [r.get("probability_global", np.nan) for r in rows],
            "s--", label="global over/underbuild track")
    ax.axhline(summary["reliable_probability"], ls="--", c="gray",
               label=f"{summary['reliable_probability']:.0%}")
    if summary["smallest_reliable_size"] is not None:
        ax.axvline(summary["smallest_reliable_size"], ls=":", c="tab:green",
                   label=f"smallest reliable: {summary['smallest_reliable_size']:g}")
    control = summary.get("control")
    if control:
        ax.plot([], [], " ", label=f"fault-free control, {control['n']} seeds: "
                f"{control['false_tracks']} false tracks, "
                f"{control['realtime_false_alarms']} false RT alarms")
    ax.set_xlabel(f"fault {param}")
    ax.set_ylabel("detection probability")
    ax.set_ylim(-0.05, 1.05)
    ax.set_title(title or "Detection probability against defect size")
    ax.legend(loc="lower right")
    fig.tight_layout()
    path = Path(path)
    fig.savefig(path, dpi=110)
    plt.close(fig)
    return path
