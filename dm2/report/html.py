"""index.html as an inspection sheet: verdict first, then truth and expectations (when
present), overview figure, track x layer timeline, track table, map thumbnails, real-time
alarms, per-layer statistics and the files. One file, no scripts, no network: the overview
and the timeline are embedded; thumbnails link to the PNG files beside it.
"""

from __future__ import annotations

import base64
from html import escape
from pathlib import Path

from dm2.report import summary
from dm2.report.report_json import DEFECT_MIN_HEIGHT_MM

STYLE = (
    "body{font-family:system-ui,sans-serif;margin:1.2em 2em;max-width:1250px;color:#222}"
    "h1{font-size:1.35em;margin:0 0 .2em}h2{font-size:1.1em;margin:1.4em 0 .4em}"
    ".meta{color:#666;font-size:.85em;margin:0 0 .8em}"
    "#verdict{border-left:6px solid #2e7d32;background:#f1f8f1;padding:.6em 1em;margin:.4em 0}"
    "#verdict.defect{border-color:#b2182b;background:#fbf0f0}"
    "#verdict p{margin:.2em 0;font-size:1.05em}#verdict ol{margin:.3em 0 .2em 1.2em;padding:0}"
    "#verdict li{margin:.15em 0}"
    "table{border-collapse:collapse;margin:.5em 0;font-size:.85em}"
    "td,th{border:1px solid #ccc;padding:2px 7px;text-align:right}th{background:#f3f3f3}"
    "td.l,th.l{text-align:left}.ok{color:#2e7d32}.no{color:#b2182b;font-weight:bold}"
    "figure{margin:.5em 0}figcaption{font-size:.8em;color:#555}"
    "#overview img{max-width:100%;width:760px}#timeline img{max-width:100%}"
    ".thumbs a{display:inline-block;margin:3px;text-align:center;font-size:.75em;color:#333}"
    ".thumbs img{width:210px;border:1px solid #ccc;display:block}"
    ".scroll{max-height:420px;overflow:auto;display:inline-block}")


def _cell(c, left=False) -> str:
    return f"<td class='l'>{escape(str(c))}</td>" if left else f"<td>{escape(str(c))}</td>"


def _table(rows: list[list], header: list[str], left: tuple[int, ...] = (),
           scroll: bool = False, tid: str | None = None) -> str:
    head = "".join(f"<th class='{'l' if i in left else ''}'>{escape(str(h))}</th>"
                   for i, h in enumerate(header))
    body = "".join("<tr>" + "".join(_cell(c, i in left) for i, c in enumerate(r)) + "</tr>"
                   for r in rows)
    attr = f" id='{tid}'" if tid else ""
    table = f"<table{attr}><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"
    return f"<div class='scroll'>{table}</div>" if scroll else table


def _img_src(root: Path | None, rel: str) -> str:
    """A data URI of ``root/rel`` (the page stands alone) or the relative link."""
    if root is not None and (Path(root) / rel).is_file():
        data = base64.b64encode((Path(root) / rel).read_bytes()).decode("ascii")
        return f"data:image/png;base64,{data}"
    return escape(rel)


def _verdict(report: dict) -> str:
    v = summary.verdict(report)
    cls = " class='defect'" if v["defects"] else ""
    items = "".join(f"<li>{escape(s)}</li>" for s in v["sentences"])
    more = (f"<p>… and {v['more']} more defect track{'s' if v['more'] != 1 else ''} in the "
            "table below.</p>" if v["more"] else "")
    return (f"<section id='verdict'{cls}><p><b>{escape(v['headline'])}</b></p>"
            + (f"<ol>{items}</ol>" if items else "") + more + "</section>")


def _blank(value) -> str:
    return "" if value is None else str(value)


def drift_sentences(report: dict) -> list[str]:
    """One sentence per track that no injected fault explains and where the twin's true surface
    stands off the reference the run used (report.json ``track_truth`` ``drift_since_layer``,
    dm2.bench.reconstruction.truth_checks), e.g. "Track 1 (overbuild) is drift: the part runs
    0.15 mm/layer over the plan since layer 62 (+0.80 mm in layer 70, beyond 0.4 mm under 100 %
    of the track)"."""
    explained = {r.get("track_id") for r in report.get("fault_truth") or []}
    kinds = {int(t["id"]): t["kind"] for t in report.get("tracks", [])}
    out = []
    for tid, tt in sorted((report.get("track_truth") or {}).items(), key=lambda e: int(e[0])):
        since = tt.get("drift_since_layer")
        if since is None or int(tid) in explained or str(tid) in map(str, explained):
            continue
        offsets = tt.get("true_offset_median_by_layer_mm") or {}
        last = max(offsets, key=int) if offsets else None
        rate = tt.get("drift_rate_mm_per_layer")
        runs = ("runs off the plan" if rate is None else
                f"runs {abs(rate):.2f} mm/layer {'over' if rate >= 0 else 'under'} the plan")
        at = f"{offsets[last]:+.2f} mm in layer {last}, " if last is not None else ""
        out.append(f"Track {tid} ({kinds.get(int(tid), '?').replace('_', ' ')}) is drift: the "
                   f"part {runs} since layer {since} ({at}beyond "
                   f"{tt.get('drift_tolerance_mm', 0.0):g} mm under "
                   f"{100 * tt.get('drift_share', 0.0):.0f} % of the track)")
    return out


def _truth(report: dict) -> str:
    parts = []
    if report.get("fault_truth"):
        onset_mm = f"{DEFECT_MIN_HEIGHT_MM:g} mm"
        rows = []
        for r in report["fault_truth"]:
            f = r["fault"]
            layers = f.get("layers") or []
            rows.append([f.get("kind"), r.get("expected_kind") or "",
                         f"{min(layers)}–{max(layers)}" if layers else "",
                         _blank(r.get("truth_onset_layer")),
                         "yes" if r["detected"] else "NO", r.get("track_id") or "",
                         _blank(r.get("first_layer_detected")),
                         _blank(r.get("onset_delay_layers"))])
        parts.append("<h2>Injected faults (the twin's truth)</h2>" + _table(
            rows, ["fault", "expected track", "layers", f"truth ≥ {onset_mm} from", "found",
                   "track", "first layer found", f"delay after truth ≥ {onset_mm} [layers]"],
            left=(0, 1)))
    drift = drift_sentences(report)
    if drift:
        parts.append("<h2>Drift (the twin's truth)</h2><ul>"
                     + "".join(f"<li>{escape(d)}.</li>" for d in drift) + "</ul>")
    if report.get("expectations"):
        rows = [[e["expect"], "met" if e["passed"] else "MISSED",
                 "; ".join(filter(None, [", ".join(str(i) for i in e.get("track_ids") or [])]
                                  + [f"process finding: {f}" for f in e.get("findings") or []]))]
                for e in report["expectations"]]
        parts.append("<h2>Expectations</h2>" + _table(rows, ["expectation", "result",
                                                             "tracks or findings"], left=(0, 2)))
    return "".join(parts)


def _track_table(ranked: list[dict]) -> str:
    if not ranked:
        return "<h2>Tracks</h2><p>No tracks.</p>"
    has_classes = any(t.get("class_history") for t in ranked)
    rows = []
    for t in ranked:
        x, y = summary.location_mm(t)
        row = [t["id"], t["kind"].replace("_", " "), f"({x:.1f}, {y:.1f})", t["first_layer"],
               t["last_layer"], len(t["history"]), f"{summary.peak_area_mm2(t):.1f}",
               f"{summary.peak_deviation_mm(t):+.2f}", summary.trend_phrase(t)]
        if has_classes:
            row.append(" → ".join(str(c) for c in t["class_history"]))
        rows.append(row)
    header = ["#", "kind", "centroid x, y [mm]", "first layer", "last layer", "layers seen",
              "peak area [mm²]", "max |deviation| [mm]", "trend"]
    if has_classes:
        header.append("class history")
    return (f"<h2>Tracks ({len(ranked)}, most severe first)</h2>"
            + _table(rows, header, left=(1, 8, 9), scroll=len(rows) > 25, tid="tracks"))


def _alarms(report: dict, ranked: list[dict]) -> str:
    rt = report.get("realtime") or {}
    alarms = rt.get("alarms") or []
    head = "<h2>Real-time alarms"
    if rt.get("latency_ms_p99") is not None:
        lat = (f" — {rt['frame_sets']} frame sets compared, latency p50 "
               f"{rt['latency_ms_p50']:.1f} ms, p99 {rt['latency_ms_p99']:.1f} ms")
    else:
        lat = ""
    if not alarms:
        return f"{head} (none)</h2><p class='meta'>{escape(lat)}</p>"
    layers = summary.alarm_layers(report)
    rows = []
    for a, lay in zip(alarms, layers, strict=True):
        tid = summary.alarm_track(a, lay, ranked)
        rows.append([f"{a['stamp_s']:.2f}", "" if lay is None else lay, a["kind"],
                     f"{a['area_mm2']:.1f}", "({:.1f}, {:.1f})".format(*a["centroid_xy_O_mm"]),
                     f"{a['delay_s']:.2f}", "" if tid is None else tid])
    return (f"{head} ({len(alarms)})</h2><p class='meta'>{escape(lat)}</p>"
            + _table(rows, ["time [s]", "layer", "kind", "area [mm²]", "centroid x, y [mm]",
                            "delay after first flag [s]", "track"], left=(2,),
                     scroll=len(rows) > 20, tid="alarms"))


def _thumbs(paths: list[str], title: str) -> str:
    if not paths:
        return ""
    items = "".join(f'<a href="{escape(p)}" target="_blank"><img src="{escape(p)}" '
                    f'alt="{escape(p)}" loading="lazy">{escape(Path(p).stem)}</a>'
                    for p in paths)
    return f"<h2>{escape(title)}</h2><div class='thumbs'>{items}</div>"


def _layers(report: dict) -> str:
    recon = report.get("reconstruction") or {}
    rows = []
    for layer in report.get("layers", []):
        st = layer["statistics"]
        row = [layer["layer"], st.get("n_vertices"), f"{st.get('deviation_min_mm') or 0:.3f}",
               f"{st.get('deviation_max_mm') or 0:.3f}", len(layer["regions"])]
        if recon:
            rec = recon.get(str(layer["layer"]))
            row.append("" if rec is None else f"{rec['rms_mm']:.3f}")
        rows.append(row)
    header = ["layer", "vertices", "min dev [mm]", "max dev [mm]", "regions"]
    if recon:
        header.append("RMS to true surface [mm]")
    return "<h2>Layers</h2>" + _table(rows, header, scroll=len(rows) > 25)


def render_index(report: dict, title: str = "3D-DM2 inspection sheet",
                 root: str | Path | None = None) -> str:
    """HTML text of ``index.html`` from the report dict; with ``root`` (the report folder) the
    overview and timeline figures are embedded, so the page needs nothing beside it."""
    files = report.get("files", {})
    ranked = summary.by_severity(report.get("tracks", []))
    meta = report.get("meta", {})
    meta_line = " · ".join(f"{k}: {v}" for k, v in meta.items() if v not in (None, ""))
    parts = [f"<h1>{escape(title)}</h1><p class='meta'>{escape(meta_line)}</p>",
             _verdict(report), _truth(report)]
    figures = files.get("figures", [])
    if "plots/overview.png" in figures:
        parts.append("<figure id='overview'><img alt='overview: last layer deviation map' "
                     f"src='{_img_src(root, 'plots/overview.png')}'><figcaption>Last layer's "
                     "signed deviation (blue under, red over the reference, ±limit), the "
                     "planned outline dashed, the most severe tracks as numbered markers "
                     "(numbers = # in the table).</figcaption></figure>")
    if "plots/timeline.png" in figures:
        parts.append("<h2>Timeline</h2><figure id='timeline'><img alt='track by layer "
                     f"timeline' src='{_img_src(root, 'plots/timeline.png')}'><figcaption>One "
                     "row per track (most severe tracks), a bar per layer it was seen, "
                     "triangles: real-time alarms.</figcaption></figure>")
    parts.append(_track_table(ranked))
    parts.append(_thumbs(files.get("track_plots", []), "Most severe tracks: area and height "
                                                       "per layer"))
    parts.append(_thumbs(files.get("deviation_maps", []), "Deviation maps (click to enlarge)"))
    parts.append(_alarms(report, ranked))
    parts.append(_layers(report))
    links = [("report.json", "report.json"), ("tracks.csv", "tracks.csv"),
             ("config.toml", "resolved configuration")]
    links += [(p, p) for p in files.get("meshes", []) + files.get("reference", [])]
    parts.append("<h2>Files</h2><ul>" + "".join(
        f'<li><a href="{escape(h)}">{escape(t)}</a></li>' for h, t in links) + "</ul>")
    if report.get("dropped"):
        parts.append("<h2>Dropped input</h2>" + _table(
            [[k, v] for k, v in report["dropped"].items()], ["reason", "count"], left=(0,)))
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{escape(title)}</title>"
            f"<style>{STYLE}</style></head><body>{''.join(parts)}</body></html>\n")
