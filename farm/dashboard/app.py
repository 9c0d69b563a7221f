"""``farm dashboard``: the web server over the farm's stores and the trainer's runs.

Routes: ``/`` (jobs, ``?status=`` filters), ``/job/<name>`` (``?fragment=1``: the part that
refreshes), ``/thumb/<name>?sample=i`` (a tonemapped render, as ``shards show``),
``/sheet/<name>?sample=i`` (its contact sheet), ``POST /cancel/<name>``, ``/runs``,
``/runfile/<name>?file=eval.png|val.png``, ``/metrics``, ``/api/job/<name>`` (JSON). A
store's or a run's ``<name>`` is ``<root index>[/<path below the root>]``; pages and metrics
show it as the root as given on the command line plus that path (its ``label``). Reads are
blocking (zarr, fsspec) and run in a thread pool so one slow store does not hold the others.
"""

from __future__ import annotations

import asyncio
import functools
import io
import json
from pathlib import Path

from aiohttp import web
from prometheus_client import CONTENT_TYPE_LATEST, CollectorRegistry, generate_latest

from farm.cancel import request_cancel
from farm.dashboard import jobs, pages, runs
from farm.dashboard.metrics import Collector
from render_jobs.contact_sheet import contact_sheet
from render_jobs.results import ScreenMaps
from render_jobs.tonemap import to_uint8, tonemap
from shaderball.web import Refused, application, confine
from storage.backend import Backend
from storage.reader import Store
from trainer import runfiles

THUMB_CACHE = 256


class Dashboard:
    def __init__(self, roots: list[str], run_dirs: list[str]):
        # a root given twice would list its stores twice under one label
        self.roots = [jobs.Root(i, r) for i, r in enumerate(dict.fromkeys(roots))]
        self.run_dirs = [Path(r) for r in dict.fromkeys(run_dirs)]
        self.samples = jobs.PerSample()

    # ---- names ----------------------------------------------------------------------------

    def _root(self, name: str) -> tuple[jobs.Root, str]:
        index, _, rel = name.partition("/")
        if not index.isdigit() or int(index) >= len(self.roots):
            raise Refused(name)
        return self.roots[int(index)], rel or "."

    def store_url(self, name: str) -> str:
        root, rel = self._root(name)
        return root.store_url(rel)

    def job_row(self, name: str) -> dict:
        root, rel = self._root(name)
        return jobs.job_row(name, root.store_url(rel), jobs.label(root.url, rel))

    def run_path(self, name: str) -> Path:
        index, _, rel = name.partition("/")
        if not index.isdigit() or int(index) >= len(self.run_dirs):
            raise Refused(name)
        return confine(self.run_dirs[int(index)], rel or ".")

    # ---- data -----------------------------------------------------------------------------

    def job_rows(self) -> list[dict]:
        rows = []
        for root in self.roots:
            try:
                names = root.find()
            except Exception as exc:  # noqa: BLE001 - an unreachable root shows as a row
                rows.append({"name": str(root.index), "label": root.url,
                             "error": f"{root.url}: {exc}"})  # fmt: skip
                continue
            for rel in names:
                name = str(root.index) if rel == "." else f"{root.index}/{rel}"
                try:
                    url = root.store_url(rel)
                except Refused:  # a symlink that leads outside the root: not served
                    continue
                rows.append(jobs.job_row(name, url, jobs.label(root.url, rel)))
        rows.sort(key=lambda r: -(r.get("started") or 0))
        return rows

    def run_rows(self) -> list[dict]:
        out = []
        for i, base in enumerate(self.run_dirs):
            for rel in runs.find_runs(base):
                name = str(i) if rel == "." else f"{i}/{rel}"
                try:
                    path = self.run_path(name)
                except Refused:  # a symlink that leads outside the folder: not served
                    continue
                out.append(runs.run_summary(name, path, jobs.label(str(base), rel)))
        return out

    def frame_seconds(self, row: dict):
        """Render seconds of the committed frames (``None``: the store cannot be read)."""
        try:
            store = Store(row["url"])
            return self.samples.get(store, set(jobs.commit_times(store.backend)))["seconds"]
        except Exception:  # noqa: BLE001 - no histogram for a store that cannot be read
            return None

    def job_context(self, name: str) -> dict:
        row = self.job_row(name)
        url = row["url"]
        ctx = {"row": row, "title": row["label"], "state": row.get("state")}
        if row["error"]:
            return ctx
        store = Store(url)
        times = jobs.commit_times(store.backend)
        state = row.get("state")
        settings = [("url", url), *sorted(store.layout.to_dict().items())]
        shown = {"sources", *store.layout.to_dict()}
        settings += [(k, v) for k, v in sorted(store.settings.items()) if k not in shown]
        settings.append(("sources", ", ".join(store.settings.get("sources", []))))
        hists = jobs.histograms(self.samples.get(store, set(times)))
        ctx.update(
            committed=len(times),
            chart=pages.line_chart(jobs.rates(state.get("history", [])) if state else []),
            shard_map=pages.shard_map(
                jobs.shard_states(store, set(times), jobs.shards_with_bytes(store.backend), state)
            ),
            thumbs=jobs.newest_samples(store, times),
            failures=jobs.failures_table(state) if state else [],
            workers=jobs.workers_table(state) if state else [],
            settings=settings,
            hists=[(k, pages.bar_chart(v)) for k, v in hists.items()],
        )
        return ctx

    @functools.lru_cache(maxsize=THUMB_CACHE)  # noqa: B019 - one dashboard per process
    def picture(self, url: str, sample: int, sheet: bool) -> bytes:
        from PIL import Image

        s = Store(url).sample(sample)
        if sheet:
            title = f"sample {s.index}  material {s.material_index} ({s.kind}: {s.source_id})"
            img = contact_sheet(ScreenMaps(**s.maps), [(s.render, s.sun.label())], title)
        else:
            img = Image.fromarray(to_uint8(tonemap(s.render)))
        buf = io.BytesIO()
        img.save(buf, format="PNG")
        return buf.getvalue()


def _blocking(fn, *args):
    return asyncio.get_running_loop().run_in_executor(None, functools.partial(fn, *args))


class Handlers:
    """The dashboard's request handlers, a method each; ``secret`` goes into every page for
    its POSTs (:func:`shaderball.web.application`)."""

    def __init__(self, dash: Dashboard, secret: str):
        self.dash, self.secret = dash, secret

    def _html(self, page: str, **ctx) -> web.Response:
        text = pages.render(page, secret=self.secret, **ctx)
        return web.Response(text=text, content_type="text/html")

    async def index(self, request):
        rows = await _blocking(self.dash.job_rows)
        want = request.query.get("status")
        if want:
            rows = [r for r in rows if r.get("status") == want]
        roots = [root.url for root in self.dash.roots]
        return self._html("jobs", rows=rows, statuses=jobs.STATUSES, title="jobs", want=want,
                          roots=roots)  # fmt: skip

    async def job(self, request):
        ctx = await _blocking(self.dash.job_context, request.match_info["name"])
        return self._html("job_live" if request.query.get("fragment") else "job", **ctx)

    async def api_job(self, request):
        row = await _blocking(self.dash.job_row, request.match_info["name"])
        return web.json_response(row, dumps=lambda o: json.dumps(o, default=str))

    async def _picture(self, request, sheet: bool):
        url = self.dash.store_url(request.match_info["name"])
        try:
            sample = int(request.query.get("sample", ""))
            body = await _blocking(self.dash.picture, url, sample, sheet)
        except (ValueError, IndexError, KeyError) as exc:
            return web.Response(status=404, text=f"404: {exc}\n")
        return web.Response(body=body, content_type="image/png")

    async def thumb(self, request):
        return await self._picture(request, sheet=False)

    async def sheet(self, request):
        return await self._picture(request, sheet=True)

    async def cancel(self, request):
        name = request.match_info["name"]
        url = self.dash.store_url(name)
        st = (await _blocking(self.dash.job_row, name)).get("status")
        if st != "running":
            return web.Response(status=409, text=f"the job is {st}, not running")
        await _blocking(request_cancel, Backend(url), "dashboard")
        return web.Response(text="cancel requested: the driver stops within a few seconds")

    async def runs_page(self, request):
        rows = await _blocking(self.dash.run_rows)
        return self._html("runs", runs=rows, title="runs", **_runs_page(rows))

    async def run_file(self, request):
        name = request.query.get("file")
        if name not in (runfiles.EVAL_GRID, runfiles.VAL_GRID):
            return web.Response(status=404, text="404\n")
        path = self.dash.run_path(request.match_info["name"]) / name
        if not path.is_file():
            return web.Response(status=404, text="404\n")
        return web.FileResponse(path)

    async def metrics(self, request):
        registry = CollectorRegistry()
        registry.register(
            Collector(self.dash.job_rows, self.dash.run_rows, self.dash.frame_seconds)
        )
        body = await _blocking(generate_latest, registry)
        return web.Response(body=body, headers={"Content-Type": CONTENT_TYPE_LATEST})


def make_app(dash: Dashboard, token: str | None) -> web.Application:
    app, secret = application(token)
    h = Handlers(dash, secret)
    app.add_routes(
        [
            web.get("/", h.index),
            web.get("/job/{name:.+}", h.job),
            web.get("/api/job/{name:.+}", h.api_job),
            web.get("/thumb/{name:.+}", h.thumb),
            web.get("/sheet/{name:.+}", h.sheet),
            web.post("/cancel/{name:.+}", h.cancel),
            web.get("/runs", h.runs_page),
            web.get("/runfile/{name:.+}", h.run_file),
            web.get("/metrics", h.metrics),
        ]
    )
    return app


def _runs_page(rows: list[dict]) -> dict:
    """The runs page's parts beyond the rows: each run's curves (into its row), the chart
    that compares their held-out scores, the settings that differ, the commands to compare
    and fine-tune them."""
    for r in rows:
        r["curves"] = _run_curves(r)
    scored = [(r["label"], [(x["step"], x["psnr"]) for x in r["val"] if "psnr" in x])
              for r in rows]  # fmt: skip
    compare = pages.lines_chart(scored) if sum(len(p) > 1 for _, p in scored) > 1 else None
    sets = {r["settings"].get(runs.HELDOUT) for r in rows if r["val"]}
    return {
        "compare": compare,
        "differ": runs.differing([r for r in rows if r["settings"]]),
        "mixed": compare is not None and len(sets) > 1,
        "commands": runs.compare_commands(rows),
        "tuned": runs.finetune_commands(rows),
    }


#: the runs page's curves: (the run's rows, the value, its title, whether y starts at 0)
RUN_CURVES = (
    ("log", "loss", "loss", True),
    ("val", "psnr", "held-out PSNR (dB)", False),
    ("log", "images_per_second", "images/s", True),
    ("log", "data_wait", "data wait (share of the time)", True),
)


def _run_curves(run: dict) -> list[tuple]:
    """``(title, SVG)`` of each of :data:`RUN_CURVES` over the run's steps (held-out scores
    only when the run has some). A run that averages its weights scores the trained weights
    too (``trained_psnr``): its held-out chart has both lines. Otherwise the held-out PSNR's
    interval over the materials (``psnr_low``, ``psnr_high``) is a band around its line."""
    charts = []
    for rows, k, title, zero in RUN_CURVES:
        if rows != "log" and not run[rows]:
            continue
        points = [(x["step"], x[k]) for x in run[rows] if k in x]
        trained = [(x["step"], x["trained_psnr"]) for x in run[rows] if "trained_psnr" in x]
        if trained:  # only score lines carry it
            series = [("moving average (renders)", points), ("trained weights", trained)]
            charts.append((title, pages.lines_chart(series, h=160)))
        else:
            band = [(x["step"], x["psnr_low"], x["psnr_high"]) for x in run[rows]
                    if k == "psnr" and x.get("psnr_low") is not None]  # fmt: skip
            charts.append((title, pages.line_chart(points, steps=True, from_zero=zero, band=band)))
    return charts
