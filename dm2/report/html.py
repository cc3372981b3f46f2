"""index.html: a static summary page linking every output of a run folder."""

from __future__ import annotations

from html import escape


def _table(rows: list[list], header: list[str]) -> str:
    head = "".join(f"<th>{escape(str(h))}</th>" for h in header)
    body = "".join("<tr>" + "".join(f"<td>{escape(str(c))}</td>" for c in r) + "</tr>"
                   for r in rows)
    return f"<table><thead><tr>{head}</tr></thead><tbody>{body}</tbody></table>"


def render_index(report: dict, title: str = "3D-DM2 run report") -> str:
    """HTML text for ``index.html`` from the report dict (its ``files`` section links)."""
    files = report.get("files", {})
    parts = [f"<h1>{escape(title)}</h1>"]
    meta = report.get("meta", {})
    if meta:
        parts.append(_table([[k, v] for k, v in meta.items()], ["", ""]))
    tracks = report.get("tracks", [])
    parts.append(f"<h2>Tracks ({len(tracks)})</h2>")
    if tracks:
        rows = [[t["id"], t["kind"], t["first_layer"], t["last_layer"], t["trend"],
                 f"{max(t['area_mm2'].values()):.1f}", f"{max(t['height_mm'].values()):.3f}"]
                for t in tracks]
        parts.append(_table(rows, ["id", "kind", "first layer", "last layer", "trend",
                                   "max area [mm2]", "max height [mm]"]))
    else:
        parts.append("<p>No defect tracks.</p>")
    for img in files.get("track_plots", []):
        parts.append(f'<img src="{escape(img)}" alt="{escape(img)}">')
    for key, label in (("fault_truth", "Injected faults"), ("expectations", "Expectations")):
        if key in report:
            rows = [[r.get("expect") or r["fault"].get("kind"),
                     "yes" if r.get("passed", r.get("detected")) else "NO",
                     r.get("track_id", r.get("track_ids"))] for r in report[key]]
            parts.append(f"<h2>{label}</h2>" + _table(rows, ["item", "met", "track"]))
    parts.append("<h2>Layers</h2>")
    rows = []
    for layer in report.get("layers", []):
        st = layer["statistics"]
        rows.append([layer["layer"], st.get("n_vertices"), f"{st.get('deviation_min_mm') or 0:.3f}",
                     f"{st.get('deviation_max_mm') or 0:.3f}", len(layer["regions"])])
    parts.append(_table(rows, ["layer", "vertices", "min dev [mm]", "max dev [mm]", "regions"]))
    for img in files.get("deviation_maps", []):
        parts.append(f'<img src="{escape(img)}" alt="{escape(img)}">')
    links = [("report.json", "report.json"), ("tracks.csv", "tracks.csv"),
             ("config.toml", "resolved configuration")]
    links += [(p, p) for p in files.get("meshes", [])]
    links += [(p, p) for p in files.get("reference", [])]
    parts.append("<h2>Files</h2><ul>" + "".join(
        f'<li><a href="{escape(h)}">{escape(t)}</a></li>' for h, t in links) + "</ul>")
    if report.get("dropped"):
        parts.append("<h2>Dropped input</h2>" + _table(
            [[k, v] for k, v in report["dropped"].items()], ["reason", "count"]))
    style = ("body{font-family:sans-serif;margin:2em;max-width:1100px}"
             "table{border-collapse:collapse;margin:1em 0}td,th{border:1px solid #ccc;"
             "padding:3px 8px}img{max-width:48%;margin:4px}")
    return (f"<!DOCTYPE html><html><head><meta charset='utf-8'><title>{escape(title)}</title>"
            f"<style>{style}</style></head><body>{''.join(parts)}</body></html>\n")
