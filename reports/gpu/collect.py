#!/usr/bin/env python3
"""The GPU script's deadline guard and collection (reports/gpu/run.sh): what a device run returns is small
files only -- metrics, logs and ``meta.json`` -- never artifacts (the 2026-11-27 run lost every score because
its archive of artifacts was 114 MB, over the size a returned file may have).

Three subcommands, each called by run.sh:

``begin``   writes ``$OUT/meta.json`` at once (status ``running``: date, card, code commit, sections asked for,
            deadline), so a run killed from outside still returns what it was; torch and CUDA versions are asked
            in the background and filled in by ``finish``.
``run``     runs one section's command in a process group of its own under a budget: the budget is
            ``min(--budget, end - now - reserve)``; the group is sent SIGTERM ``--grace`` seconds before it runs
            out, SIGKILL when it does, and any process it left behind is killed when it returns.  The token
            ``{deadline}`` in the command becomes the budget less ``--margin`` (at most a quarter of it): a
            deadline the command can keep itself (dagrun.py stops launching and writes its timings).
            Appends a line to ``WORK/sections.jsonl``.
``finish``  gathers the small files of WORK (and of a DAG project copy), cuts the largest logs to their
            tails while they exceed :data:`LIMIT_BYTES`, then drops the largest remaining files (each named in
            meta.json), writes ``$OUT/results.tar.gz``, the headline JSONs beside it, and the final meta.json.

Standard library only (pandas optional, for Parquet-to-JSON): it must run on the device's bare Python
before, and whatever becomes of, the project's wheels.
"""

from __future__ import annotations

import argparse
import io
import json
import os
import platform
import signal
import subprocess
import sys
import tarfile
import time
from datetime import datetime, timezone
from pathlib import Path

#: the collected set is cut to this size (a returned file may have 16 MiB; the issue asks < 5 MB in all)
LIMIT_BYTES = 4_500_000
#: a cut log keeps this many bytes of its end
TAIL_BYTES = 20_000
#: returned from the device: letters, digits, '.', '_' and '-' only, at most 8 files (device README)
MAX_RETURNED_FILES = 8
#: collected suffixes: metrics, tables, reports, logs.  Never *.zarr, weights, images.
SMALL_SUFFIXES = (".json", ".jsonl", ".csv", ".md", ".log", ".txt")
#: never collected, whatever the suffix says
NEVER = (".zarr", ".safetensors", ".pt", ".pth", ".onnx", ".bin", ".png", ".svg", ".jpg", ".jpeg", ".npy", ".npz",
         ".tgz", ".gz", ".tar", ".html", ".parquet", ".xml")
#: one collected file larger than this is left out before any cut (a table dumped by mistake, not a metric)
MAX_FILE_BYTES = 8_000_000
#: a DAG project copy's tables turned into JSON records (``artifacts/<name>.parquet``)
PARQUET_SUMMARIES = ("summary", "thresholds", "teacher_metrics", "efficiency", "metrics")
#: the headline files put beside the archive as well (the rest is inside it)
HEADLINES = ("past_labels.json", "teacher_gpu.json")


def now_utc() -> str:
    return datetime.now(timezone.utc).isoformat(timespec="seconds")


def write_json(path: Path, obj) -> None:
    """Atomic: a reader (or a kill) never sees half a file."""
    tmp = path.with_name(f".{path.name}.tmp-{os.getpid()}")
    tmp.write_text(json.dumps(obj, indent=1, default=str))
    os.replace(tmp, path)


def read_json(path: Path, default=None):
    try:
        return json.loads(path.read_text())
    except (OSError, ValueError):
        return default


def _capture(cmd: list[str], timeout: float = 20) -> str | None:
    try:
        r = subprocess.run(cmd, capture_output=True, text=True, timeout=timeout)
    except (OSError, subprocess.SubprocessError):
        return None
    return r.stdout.strip() if r.returncode == 0 else None


def card() -> list[dict] | None:
    """One row per GPU from nvidia-smi (name, driver, memory); None without nvidia-smi."""
    out = _capture(["nvidia-smi", "--query-gpu=name,driver_version,memory.total", "--format=csv,noheader"])
    if not out:
        return None
    rows = [[x.strip() for x in line.split(",")] for line in out.splitlines() if line.strip()]
    return [{"name": r[0], "driver": r[1] if len(r) > 1 else None, "memory_total": r[2] if len(r) > 2 else None}
            for r in rows]


#: torch, its CUDA, and whether a GPU is seen, as the Python the sections run with says
TORCH_QUERY = ("import json, torch; print(json.dumps({'torch': torch.__version__, 'cuda': torch.version.cuda, "
               "'cuda_available': torch.cuda.is_available(), 'device_name': torch.cuda.get_device_name(0) "
               "if torch.cuda.is_available() else None}))")
TORCH_FIELDS = ("torch", "cuda", "cuda_available", "device_name")


def start_torch_query(python: str, work: Path) -> None:
    """Ask in the background (importing torch takes seconds, which the sections need more): the answer lands in
    ``work/torch.json`` and ``finish`` reads it."""
    with open(work / "torch.json", "w") as sink:
        subprocess.Popen([python, "-c", TORCH_QUERY], stdout=sink, stderr=subprocess.DEVNULL, start_new_session=True)


def torch_info(work: Path) -> dict:
    """The background query's answer; the fields set to None (and why) when it has none."""
    got = read_json(work / "torch.json")
    if not isinstance(got, dict):
        return {**dict.fromkeys(TORCH_FIELDS), "torch_note": "the torch query gave no answer in time"}
    return got


def code_commit(src: Path) -> str | None:
    """The commit the code came from: ``src/COMMIT`` (written by prepare.sh), else ``git rev-parse``."""
    f = src / "COMMIT"
    if f.is_file():
        return f.read_text().strip() or None
    return _capture(["git", "-C", str(src), "rev-parse", "HEAD"])


def settings_of(text: str) -> dict:
    """The run's settings as run.sh wrote them; kept as text when a value broke the JSON (a quote in PL_ARGS)."""
    try:
        got = json.loads(text or "{}")
    except ValueError:
        return {"unparsed": text}
    return got if isinstance(got, dict) else {"unparsed": text}


def cmd_begin(a) -> None:
    out, work = Path(a.out), Path(a.work)
    out.mkdir(parents=True, exist_ok=True)
    work.mkdir(parents=True, exist_ok=True)
    (work / "sections.jsonl").write_text("")
    start_torch_query(a.python, work)
    meta = {"status": "running", "date_utc": now_utc(), "started_epoch": a.started, "deadline_s": a.deadline,
            "collect_reserve_s": a.reserve, "card": card(), **dict.fromkeys(TORCH_FIELDS),
            "python": platform.python_version(), "cpu_count": os.cpu_count(), "host": platform.node(),
            "code_commit": code_commit(Path(a.src)), "code_dir": a.src,
            "sections_asked": a.sections.split(), "settings": settings_of(a.settings)}
    write_json(out / "meta.json", meta)
    print(f"meta: {meta['date_utc']} card {meta['card']} commit {meta['code_commit']}", flush=True)


def section_budget(budget: float | None, end: float, reserve: float, now: float) -> float:
    """Seconds a section may run: its own budget, cut to the time left before ``end`` less ``reserve``."""
    left = end - now - reserve
    return max(0.0, left if budget is None else min(budget, left))


def _killpg(pgid: int, sig: int) -> None:
    try:
        os.killpg(pgid, sig)
    except (ProcessLookupError, PermissionError):
        pass


def cmd_run(a) -> int:
    work = Path(a.work)
    (work / "logs").mkdir(parents=True, exist_ok=True)
    t0 = time.time()
    budget = section_budget(a.budget, a.end, a.reserve, t0)
    rec = {"section": a.name, "budget_s": round(budget, 1), "start_utc": now_utc()}
    # a short budget keeps three quarters of itself: the margin must not eat it all
    cmd = [c.replace("{deadline}", str(max(1, int(budget - min(a.margin, budget / 4))))) for c in a.cmd]
    if cmd and cmd[0] == "--":
        cmd = cmd[1:]
    rec["cmd"] = " ".join(cmd)
    if budget < a.min_budget:
        rec.update(rc=None, skipped=f"{budget:.0f} s left before the deadline (< {a.min_budget:.0f} s)",
                   seconds=0.0, timed_out=False)
    else:
        with open(work / "logs" / f"{a.name}.log", "ab") as log:
            p = subprocess.Popen(cmd, stdout=log, stderr=subprocess.STDOUT, cwd=a.cwd, start_new_session=True)
            timed_out = False
            grace = min(a.grace, budget / 5)  # SIGTERM this long before the budget's end, SIGKILL at it
            try:
                rc = p.wait(timeout=budget - grace)
            except subprocess.TimeoutExpired:
                timed_out = True
                _killpg(p.pid, signal.SIGTERM)
                try:
                    p.wait(timeout=grace)
                except subprocess.TimeoutExpired:
                    _killpg(p.pid, signal.SIGKILL)
                    p.wait()
                rc = p.returncode
            _killpg(p.pid, signal.SIGKILL)  # whatever the section left running must not share the next one's GPU
        rec.update(rc=rc, seconds=round(time.time() - t0, 2), timed_out=timed_out)
    with open(work / "sections.jsonl", "a") as f:
        f.write(json.dumps(rec) + "\n")
    print(f"[{a.name}] rc={rec['rc']} {rec['seconds']} s of {rec['budget_s']} s"
          + (" TIMED OUT (stopped by the guard)" if rec.get("timed_out") else "")
          + (f" skipped: {rec['skipped']}" if rec.get("skipped") else ""), flush=True)
    return 0


# --- what finished ---------------------------------------------------------------------------------------------

def dag_finished(proj: Path) -> dict | None:
    """From dagrun.py's logs/timings.json: stages finished (rc 0), failed, skipped, cut by its deadline."""
    t = read_json(proj / "logs" / "timings.json")
    if not isinstance(t, dict):
        return None
    jobs = t.get("jobs", {})
    return {"finished": sorted(k for k, v in jobs.items() if v.get("rc") == 0),
            "failed": sorted(k for k, v in jobs.items() if v.get("rc") not in (None, 0)),
            "skipped": sorted(k for k, v in jobs.items() if "skipped" in v),
            "running_at_deadline": t.get("deadline_running", []), "pending_at_deadline": t.get("deadline_pending", []),
            "unfinished": sorted(k for k, v in jobs.items() if "rc" not in v and "skipped" not in v),
            "stages": len(t.get("stages", {})), "total_s": t.get("total")}


def past_labels_finished(work: Path) -> dict | None:
    """From benchmarks.past_labels' ``<out>.runs.jsonl`` (appended as each run ends) and its final JSON."""
    partial = work / "past_labels.json.runs.jsonl"
    if not partial.exists() and not (work / "past_labels.json").exists():
        return None
    runs = []
    if partial.exists():
        for line in partial.read_text(errors="replace").splitlines():
            try:
                r = json.loads(line)
            except ValueError:
                continue
            if "variant" in r:
                runs.append({"variant": r["variant"], "seed": r.get("seed"), "iou_cal": r.get("iou_cal"),
                             "groups": r.get("groups"), "steps_run": r.get("steps_run"), "seconds": r.get("seconds")})
    final = read_json(work / "past_labels.json")
    return {"runs_finished": runs, "summary_written": isinstance(final, dict),
            "summary": final.get("summary") if isinstance(final, dict) else None}


def teacher_finished(work: Path) -> dict | None:
    t = read_json(work / "teacher_gpu.json")
    if not isinstance(t, dict):
        return None
    return {"batches_finished": sorted(int(b) for b in t.get("batches", {})), "stopped": t.get("stopped"),
            "finished": t.get("finished")}


def cut_by_own_deadline(finished: dict) -> bool:
    """Whether a section stopped at the deadline it was given (dagrun.py's, bench_teacher --batch-sweep's) with work left."""
    dag, teacher = finished.get("dag") or {}, finished.get("teacher") or {}
    return bool(dag.get("running_at_deadline") or dag.get("pending_at_deadline")
                or str(teacher.get("stopped") or "").startswith("deadline"))


# --- collection ------------------------------------------------------------------------------------------------

def small_files(base: Path, patterns: list[str]) -> list[Path]:
    """Files under ``base`` matching ``patterns`` with a small suffix, outside any ``*.zarr`` or weights."""
    found: dict[Path, None] = {}
    for pat in patterns:
        for p in sorted(base.glob(pat)):
            rel = p.relative_to(base)
            if not p.is_file() or p.is_symlink():
                continue
            if any(part.lower().endswith(NEVER) for part in rel.parts):
                continue
            if p.suffix.lower() in SMALL_SUFFIXES:
                found[p] = None
    return list(found)


def parquet_summaries(proj: Path) -> dict[str, bytes]:
    """``artifacts/<name>.parquet`` of :data:`PARQUET_SUMMARIES` as JSON records (pandas needed; skipped
    without it)."""
    out: dict[str, bytes] = {}
    try:
        import pandas as pd
    except ImportError:
        return out
    for name in PARQUET_SUMMARIES:
        f = proj / "artifacts" / f"{name}.parquet"
        if f.is_file():
            try:
                out[f"dag/artifacts/{name}.json"] = pd.read_parquet(f).to_json(orient="records").encode()
            except Exception as e:  # noqa: BLE001 -- one unreadable table must not lose the others
                out[f"dag/artifacts/{name}.error.txt"] = f"{type(e).__name__}: {e}".encode()
    return out


def gather(work: Path, proj: Path | None) -> dict[str, bytes]:
    """``{name in the archive: bytes}`` of everything worth returning."""
    files: dict[str, bytes] = {}
    for p in small_files(work, ["*", "logs/*"]):
        files[str(p.relative_to(work))] = p.read_bytes()
    if proj is not None and proj.is_dir():
        pats = ["logs/*", "reports/**/*", "dvclive/**/metrics.json", "params.yaml"]
        for p in small_files(proj, pats) + ([proj / "params.yaml"] if (proj / "params.yaml").is_file() else []):
            files["dag/" + str(p.relative_to(proj))] = p.read_bytes()
        files.update(parquet_summaries(proj))
    return files


def fit(files: dict[str, bytes], limit: int = LIMIT_BYTES, tail: int = TAIL_BYTES) -> tuple[dict, list, list]:
    """Cut ``files`` under ``limit`` bytes: oversized files out first, then the largest logs to their last
    ``tail`` bytes, then the largest remaining files out.  Returns (files, logs cut, files dropped)."""
    files = dict(files)
    dropped = [n for n, b in files.items() if len(b) > MAX_FILE_BYTES and not n.endswith((".log", ".txt"))]
    for n in dropped:
        del files[n]
    cut = []
    total = lambda: sum(len(b) for b in files.values())  # noqa: E731
    for n in sorted((n for n in files if n.endswith((".log", ".txt"))), key=lambda n: -len(files[n])):
        if total() <= limit:
            break
        if len(files[n]) > tail:
            files[n] = b"[... cut to its last %d bytes by reports/gpu/collect.py ...]\n" % tail + files[n][-tail:]
            cut.append(n)
    for n in sorted(files, key=lambda n: -len(files[n])):
        if total() <= limit:
            break
        del files[n]
        dropped.append(n)
    return files, cut, dropped


def cmd_finish(a) -> None:
    out, work = Path(a.out), Path(a.work)
    proj = Path(a.proj) if a.proj else None
    meta = read_json(out / "meta.json", {}) or {}
    sections = [json.loads(x) for x in (work / "sections.jsonl").read_text().splitlines() if x.strip()] \
        if (work / "sections.jsonl").exists() else []
    finished = {k: v for k, v in {"dag": dag_finished(proj) if proj else None,
                                  "past_labels": past_labels_finished(work),
                                  "teacher": teacher_finished(work)}.items() if v is not None}
    elapsed = time.time() - a.started if a.started else None
    files, cut, dropped = fit(gather(work, proj))
    status = "complete"
    if any(s.get("timed_out") or s.get("skipped") for s in sections) or cut_by_own_deadline(finished):
        status = "deadline"
    elif any(s.get("rc") not in (0, None) for s in sections):
        status = "failed"
    meta.update(torch_info(work))
    meta.update(status=status, end_utc=now_utc(), elapsed_s=round(elapsed, 1) if elapsed is not None else None,
                sections=sections, finished=finished, logs_cut_to_tail=cut, files_dropped=dropped,
                collected_bytes=sum(len(b) for b in files.values()), archive="results.tar.gz",
                archive_files=sorted(files))
    # the archive: deterministic order and times (same files -> same bytes)
    buf = io.BytesIO()
    with tarfile.open(fileobj=buf, mode="w:gz", compresslevel=9) as tar:
        for name in sorted(files):
            info = tarfile.TarInfo(name)
            info.size, info.mtime, info.mode = len(files[name]), 0, 0o644
            tar.addfile(info, io.BytesIO(files[name]))
    (out / "results.tar.gz").write_bytes(buf.getvalue())
    beside = [h for h in HEADLINES if h in files and len(files[h]) < 1_000_000][: MAX_RETURNED_FILES - 3]
    for h in beside:
        (out / h).write_bytes(files[h])
    if "run.log" in files:
        (out / "run.log").write_bytes(files["run.log"][-TAIL_BYTES:])
    meta["returned"] = {p.name: p.stat().st_size for p in sorted(out.iterdir()) if p.is_file() and p.name != "meta.json"}
    write_json(out / "meta.json", meta)
    total = sum(p.stat().st_size for p in out.iterdir() if p.is_file())
    print(f"collected {len(files)} files, {meta['collected_bytes']} bytes -> $OUT {total} bytes; status {status}; "
          f"logs cut: {len(cut)}, dropped: {dropped or 'none'}", flush=True)


def main(argv: list[str] | None = None) -> int:
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    sub = ap.add_subparsers(dest="what", required=True)
    b = sub.add_parser("begin")
    b.add_argument("--out", required=True)
    b.add_argument("--work", required=True)
    b.add_argument("--src", required=True)
    b.add_argument("--python", default=sys.executable)
    b.add_argument("--deadline", type=float, required=True)
    b.add_argument("--reserve", type=float, required=True)
    b.add_argument("--started", type=float, required=True)
    b.add_argument("--sections", default="")
    b.add_argument("--settings", default="{}", help="a JSON object of the run's settings (WINNER, sizes, ...)")
    r = sub.add_parser("run")
    r.add_argument("--work", required=True)
    r.add_argument("--name", required=True)
    r.add_argument("--end", type=float, required=True, help="epoch seconds of the whole run's deadline")
    r.add_argument("--reserve", type=float, default=20.0, help="seconds kept for the collection")
    r.add_argument("--budget", type=float, default=None, help="the section's own cap (seconds)")
    r.add_argument("--margin", type=float, default=15.0, help="{deadline} = budget - margin")
    r.add_argument("--grace", type=float, default=5.0, help="SIGTERM -> SIGKILL (at most a fifth of the budget)")
    r.add_argument("--min-budget", type=float, default=5.0, help="skip the section with less time than this")
    r.add_argument("--cwd", default=None)
    r.add_argument("cmd", nargs=argparse.REMAINDER)
    f = sub.add_parser("finish")
    f.add_argument("--out", required=True)
    f.add_argument("--work", required=True)
    f.add_argument("--proj", default=None)
    f.add_argument("--started", type=float, default=None)
    a = ap.parse_args(argv)
    return {"begin": cmd_begin, "run": cmd_run, "finish": cmd_finish}[a.what](a) or 0


if __name__ == "__main__":
    sys.exit(main())
