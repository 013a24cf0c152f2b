"""`monostixels batch`: many clips in parallel on Ray, into one Parquet dataset.

``monostixels batch batch.inputs=DIR_OR_GLOB batch.output=DIR`` runs every clip (a video file, or a
folder of images with its intrinsics file) as one Ray task and writes
(docs/conventions.md, section 4.6):

- ``DIR/stixels.parquet/clip=<name>/part-0.parquet``: a Parquet dataset partitioned by clip
  (hive layout), one row per stixel per frame, columns :data:`SCHEMA_FIELDS` (the writer
  :class:`monostixels.output.writers.StixelRows`);
- ``DIR/summary.json``: per clip its input, frames, status (``ok`` | ``failed``), error and seconds (and
  ``skipped_frames``, the unreadable frames skipped, where there were any).

A clip that fails (unreadable, too short, no intrinsics...) is recorded with its reason while the
others go on. A second run into the same ``DIR`` skips the clips already there (and those that
failed, unless ``batch.retry_failed=true``). Ray: a local instance with ``batch.num_cpus``
workers, or a running cluster at ``batch.address``. Needs the optional extra
``pip install -e ".[batch]"`` (ray, pyarrow).
"""
from __future__ import annotations

import hashlib
import json
import logging
import os
import re
import sys
import time
from dataclasses import dataclass, field
from glob import glob
from pathlib import Path
from typing import Any, List, Optional, Sequence

from monostixels._checks import InputError, config_params
from monostixels._threads import set_threads
from monostixels.data._readers import IMAGE_EXTENSIONS
from monostixels.data.base import source_info
# SCHEMA_FIELDS and frame_rows: the dataset's columns, named here as before (docs/conventions.md, section 4.6).
from monostixels.output.writers import SCHEMA_FIELDS, frame_rows  # noqa: F401
from monostixels.output.writers import StixelRows, write_partition, write_sequence

__all__ = ["BatchConfig", "Clip", "SCHEMA_FIELDS", "discover_clips", "clip_data_config", "process_clip", "read_summary",
           "run_batch"]

logger = logging.getLogger(__name__)

SUMMARY_NAME = "summary.json"
DATASET_NAME = "stixels.parquet"
SUMMARY_FORMAT = "monostixels-batch/1"
#: Intrinsics files beside a video ``clip.mp4`` that the batch uses for it: ``clip.intrinsics.yaml`` ...
_SIDECAR_SUFFIXES = (".intrinsics.yaml", ".intrinsics.yml", ".intrinsics.json", ".intrinsics.txt")

@dataclass
class BatchConfig:
    """The settings of ``monostixels batch``: the schema of the config group ``batch`` (monostixels.config_schema).

    Attributes:
        inputs: the clips: a folder (each video file and each sub-folder of images in it is a clip), a glob
            (each match: a video file or a folder of images), or a list of them (:func:`discover_clips`).
            Folders of images carry their own intrinsics file (as ``data=frames``); videos use
            ``data.intrinsics`` / ``data.hfov_deg``, or a file ``<video stem>.intrinsics.{yaml,yml,json,txt}``
            beside them. Every other ``data.*`` option applies to every clip.
        output: output folder: ``<output>/stixels.parquet/clip=<name>/`` and ``<output>/summary.json``.
        address: Ray: None = start a local Ray instance with ``num_cpus`` workers; an address joins a running
            cluster (``auto`` on one of its nodes, ``ray://HEAD:10001`` with ray[client]).
        num_cpus: CPUs of the local Ray instance (None = every core of this machine).
        cpus_per_clip: CPUs reserved per clip (its torch / OpenCV threads).
        retry_failed: run again the clips that failed on an earlier run into ``output`` (False: they are
            skipped too, their error stays in summary.json).
        video_extensions: file extensions taken as video clips (case-insensitive).
    """

    # A folder or glob, or a list of them: no one type (discover_clips checks it).
    inputs: Any = None
    output: str = "batch"
    address: Optional[str] = None
    num_cpus: Optional[int] = None
    cpus_per_clip: int = 1
    retry_failed: bool = False
    video_extensions: List[str] = field(default_factory=lambda: [".mp4", ".avi", ".mkv", ".mov", ".m4v", ".webm"])


@dataclass(frozen=True)
class Clip:
    """One input clip: a name (its partition), its path and its kind (``video`` | ``frames``)."""

    name: str
    path: str
    kind: str


# ------------------------------------------------------------------------------------------------ inputs
def _has_images(folder: Path) -> bool:
    return any(p.is_file() and p.suffix.lower() in IMAGE_EXTENSIONS for p in folder.iterdir())


def _clip_names(paths: Sequence[Path]) -> list[str]:
    """Unique partition names of resolved clip paths: the file stems (folder names), or where two
    collide the paths relative to their common folder (``car1/front.mp4`` -> ``car1_front``, and
    ``a.mp4`` beside ``a.avi`` -> ``a.mp4``, ``a.avi``); characters outside ``[A-Za-z0-9._-]`` -> ``_``."""
    def clean(s: str) -> str:
        return re.sub(r"[^A-Za-z0-9._-]", "_", s).strip("._") or "clip"

    def unique(names: list[str]) -> bool:
        return len(set(names)) == len(names)

    names = [clean(p.stem if p.is_file() else p.name) for p in paths]
    if unique(names):
        return names
    base = Path(os.path.commonpath([str(p.parent) for p in paths]))
    rel = [p.relative_to(base) for p in paths]
    names = [clean(str(r.with_suffix("") if p.is_file() else r)) for r, p in zip(rel, paths)]
    return names if unique(names) else [clean(str(r)) for r in rel]


def discover_clips(inputs: str | Sequence[str], video_extensions: Sequence[str] = (".mp4",),
                   exclude: str | Path | None = None) -> list[Clip]:
    """The clips of ``batch.inputs``, sorted by path.

    Args:
        inputs: a folder, a glob, or a list of them. A folder that holds images is one clip (a
            folder of frames); any other folder's clips are its video files and its sub-folders that
            hold images. Each match of a glob is a video file or a folder of images.
        video_extensions: file suffixes taken as videos (case-insensitive).
        exclude: a folder never taken as a clip (the batch output).

    Raises:
        InputError: ``inputs`` unset, or nothing matches / no clip found (the message names it).
    """
    if inputs is None or (isinstance(inputs, str) and not inputs.strip()):
        raise InputError("batch.inputs: not set: give a folder of clips or a glob, e.g. batch.inputs='clips/*.mp4'")
    specs = [inputs] if isinstance(inputs, str) else [str(s) for s in inputs]
    exts = {e.lower() if e.startswith(".") else f".{e.lower()}" for e in video_extensions}
    skip = Path(exclude).resolve() if exclude is not None else None
    found: dict[Path, str] = {}
    for spec in specs:
        root = Path(spec).expanduser()
        from_glob = not root.is_dir()
        if not from_glob:
            candidates = [root] if _has_images(root) else sorted(root.iterdir())
        else:
            candidates = [Path(p) for p in sorted(glob(str(root), recursive=True))]
            if not candidates:
                raise InputError(f"batch.inputs: {spec!r} is neither a folder nor a glob that matches anything")
        for p in candidates:
            if skip is not None and p.resolve() == skip:
                continue
            if p.is_file() and p.suffix.lower() in exts:
                found[p.resolve()] = "video"
            elif p.is_dir() and _has_images(p):
                found[p.resolve()] = "frames"
            elif from_glob and not p.name.endswith(_SIDECAR_SUFFIXES):
                # In a folder, other files (notes, intrinsics) are expected; a glob asked for this one.
                logger.warning("batch.inputs: %s is neither a video (%s) nor a folder of images: skipped",
                               p, ", ".join(sorted(exts)))
    if not found:
        raise InputError(f"batch.inputs: no clips in {', '.join(specs)} (video files {', '.join(sorted(exts))} "
                         f"or folders of images)")
    paths = sorted(found)
    return [Clip(n, str(p), found[p]) for n, p in zip(_clip_names(paths), paths)]


def _packaged_data_group(name: str) -> dict[str, Any]:
    """The packaged option ``data=NAME`` (its schema's defaults and the YAML's values) as a dict."""
    from monostixels.core.energy import load_config_group

    return load_config_group("data", name)


def clip_data_config(data: Any, clip: Clip) -> dict[str, Any]:
    """The ``data`` group of one clip: the packaged ``video`` or ``frames`` group, with the user's
    ``data.*`` options that it knows (step, frames, resize, hfov_deg, camera_height...) and the clip's path.

    Intrinsics: a folder of frames uses its own file, else ``data.intrinsics``; a video uses
    ``<stem>.intrinsics.{yaml,yml,json,txt}`` beside it, else ``data.intrinsics``, else ``data.hfov_deg``.
    """
    from omegaconf import OmegaConf

    user = OmegaConf.to_container(data, resolve=True) if OmegaConf.is_config(data) else dict(data or {})
    if user.get("name") not in (None, "video", "frames"):
        raise InputError(f"batch: clips are videos or folders of frames; data={user.get('name')} cannot be "
                         f"applied to them (leave data unset, or data=video / data=frames)")
    out = _packaged_data_group(clip.kind)
    for k, v in user.items():
        if k in out and k not in ("name", "path", "root", "poses"):
            out[k] = v
    p = Path(clip.path)
    if clip.kind == "video":
        out["path"] = clip.path
        sidecar = [p.with_name(p.stem + s) for s in _SIDECAR_SUFFIXES if p.with_name(p.stem + s).is_file()]
        if sidecar:
            out["intrinsics"] = str(sidecar[0])
    else:
        from monostixels.data.frames import INTRINSICS_NAMES

        out["root"] = clip.path
        if any((p / n).is_file() for n in INTRINSICS_NAMES):
            out["intrinsics"] = None  # the folder's own file
        out["poses"] = None
    return out


# ------------------------------------------------------------------------------------------------ one clip
def process_clip(cfg: dict[str, Any], clip: Clip, threads: int = 1) -> tuple[dict[str, Any], Any]:
    """Run the pipeline on every frame pair of one clip (the body of a Ray task).

    Args:
        cfg: the composed config as a plain dict. clip: the clip. threads: torch / OpenCV threads.

    Returns:
        ``(summary, table)``: the clip's summary entry, and its rows as a ``pyarrow.Table`` (None
        where it failed). Never raises for a bad clip: the error goes into the summary.
    """
    from omegaconf import OmegaConf

    from monostixels.build import Purpose, build, build_source

    logging.getLogger("monostixels").setLevel(str(cfg.get("log_level", "INFO")))
    set_threads(max(1, int(threads)))  # the clip's CPUs: torch, OpenCV and ONNX Runtime alike
    start = time.perf_counter()
    entry: dict[str, Any] = {"input": clip.path, "kind": clip.kind, "frames": 0, "rows": 0, "status": "failed",
                             "error": None, "seconds": 0.0}
    rows: StixelRows | None = None
    try:
        conf = OmegaConf.create(cfg)
        conf.data = clip_data_config(conf.data, clip)
        src = build_source(conf)
        if len(src) == 0:
            raise InputError(f"{clip.path}: no frame pairs")
        # Built as `monostixels run` builds it (monostixels.build): the same frames, pairs, tracks and TTC.
        runner = build(conf, Purpose.RUN, source=src).runner
        rows = StixelRows(source_info(src).fps)
        write_sequence(runner.run(src), [rows])
        frames = rows.frames
        skipped = source_info(src).skipped_frames  # unreadable frames, warned about and skipped
        if skipped:
            entry["skipped_frames"] = skipped
            if frames == 0:
                raise InputError(f"{clip.path}: no frame pair could be made: {len(skipped)} unreadable frame(s) skipped")
        entry.update(frames=frames, rows=rows.table.num_rows, status="ok")
        return entry, rows.table
    except InputError as e:
        entry["error"] = str(e)
    except Exception as e:  # noqa: BLE001 — one clip's failure must not stop the batch; its reason is kept
        logger.exception("batch: clip %s failed", clip.name)
        entry["error"] = f"{type(e).__name__}: {e}"
    finally:
        entry["seconds"] = round(time.perf_counter() - start, 3)
    entry["frames"] = rows.frames if rows is not None else 0  # those written before the failure
    return entry, None


# ------------------------------------------------------------------------------------------------ the batch
def read_summary(output: str | Path) -> dict[str, Any]:
    """``DIR/summary.json`` as a dict, or an empty summary where there is none yet."""
    path = Path(output) / SUMMARY_NAME
    if not path.is_file():
        return {"format": SUMMARY_FORMAT, "settings": None, "clips": {}}
    try:
        s = json.loads(path.read_text())
    except (OSError, json.JSONDecodeError) as e:
        raise InputError(f"batch.output: cannot read {path} ({e}); remove it to start over") from e
    if s.get("format") != SUMMARY_FORMAT:
        raise InputError(f"batch.output: {path} is not a batch summary (format {s.get('format')!r})")
    return s


def _write_json(path: Path, obj: Any) -> None:
    tmp = path.with_suffix(".json.tmp")
    tmp.write_text(json.dumps(obj, indent=1))
    os.replace(tmp, path)  # a crash never leaves half a summary


def _settings(cfg: dict[str, Any]) -> str:
    """Fingerprint of everything that changes a clip's stixels (not where or how it is scheduled)."""
    keep = {k: v for k, v in cfg.items() if k not in ("batch", "command", "outputs", "out", "log_level", "output")}
    data = dict(keep.get("data") or {})
    for k in ("name", "path", "root"):  # set per clip
        data.pop(k, None)
    keep["data"] = data
    return hashlib.sha256(json.dumps(keep, sort_keys=True, default=str).encode()).hexdigest()[:16]


def _partition(output: Path, name: str) -> Path:
    return output / DATASET_NAME / f"clip={name}"


def _done(entry: dict[str, Any] | None, clip: Clip, output: Path, retry_failed: bool) -> bool:
    """Whether an earlier run finished ``clip`` (same input; its file is there, or it failed)."""
    if entry is None or entry.get("input") != clip.path:
        return False
    if entry.get("status") == "ok":
        return (_partition(output, clip.name) / "part-0.parquet").is_file()
    return entry.get("status") == "failed" and not retry_failed


def run_batch(cfg: Any) -> int:
    """``monostixels batch``: every clip of ``batch.inputs`` on Ray into ``batch.output``.

    Returns:
        0 when every clip is ok. Where a clip failed (in this run or, not retried, an earlier one),
        exits with status 1 after writing everything else and listing the failures on stderr.

    Raises:
        InputError: ray / pyarrow missing, no clips, or a ``batch.output`` written with other settings.
    """
    from omegaconf import OmegaConf
    from tqdm import tqdm

    try:
        import pyarrow  # noqa: F401
        import ray
    except ImportError as e:
        raise InputError(f'monostixels batch needs ray and pyarrow, the optional "batch" extra: '
                         f'pip install -e ".[batch]" ({e})') from e
    b = config_params(BatchConfig, cfg.get("batch"), "batch")
    output = Path(b.output).expanduser()
    clips = discover_clips(b.inputs, b.video_extensions, exclude=output)
    cfg_dict = OmegaConf.to_container(cfg, resolve=True)
    summary = read_summary(output)
    settings = _settings(cfg_dict)
    if summary["clips"] and summary.get("settings") not in (None, settings):
        raise InputError(f"batch.output: {output} holds clips made with other settings (flow, semantic, motion, "
                         f"prior, solver or data options); choose another batch.output or remove {output}")
    summary["settings"] = settings
    todo = [c for c in clips if not _done(summary["clips"].get(c.name), c, output, b.retry_failed)]
    skipped = len(clips) - len(todo)
    output.mkdir(parents=True, exist_ok=True)
    logger.info("batch: %d clip(s), %d already done, %d to run -> %s", len(clips), skipped, len(todo), output)
    threads = max(1, b.cpus_per_clip)
    if todo:
        started = not ray.is_initialized()
        if started:
            ray.init(address=b.address, num_cpus=b.num_cpus if b.address is None else None,
                     include_dashboard=False, logging_level=logging.WARNING)
        try:
            task = ray.remote(num_cpus=threads, max_retries=0)(process_clip)
            futures = {task.remote(cfg_dict, c, threads): c for c in todo}
            pending = list(futures)
            with tqdm(total=len(todo), desc="batch", unit="clip") as bar:
                while pending:
                    done, pending = ray.wait(pending, num_returns=1)
                    for f in done:
                        clip = futures[f]
                        try:
                            entry, table = ray.get(f)
                        except Exception as e:  # noqa: BLE001 — a worker that died: the clip failed
                            entry = {"input": clip.path, "kind": clip.kind, "frames": 0, "rows": 0,
                                     "status": "failed", "error": f"{type(e).__name__}: {e}", "seconds": None}
                            table = None
                        if table is not None:
                            write_partition(_partition(output, clip.name), table)
                        summary["clips"][clip.name] = entry
                        _write_json(output / SUMMARY_NAME, summary)
                        bar.set_postfix_str(f"{clip.name} {entry['status']}")
                        bar.update(1)
        finally:
            if started:
                ray.shutdown()
    else:
        _write_json(output / SUMMARY_NAME, summary)
    entries = {c.name: summary["clips"][c.name] for c in clips if c.name in summary["clips"]}
    failed = {k: e for k, e in entries.items() if e["status"] != "ok"}
    rows = sum(int(e.get("rows") or 0) for e in entries.values() if e["status"] == "ok")
    print(f"batch: {len(clips)} clip(s): {len(entries) - len(failed)} ok, {len(failed)} failed, "
          f"{len(todo)} run now, {skipped} done before -> {output / DATASET_NAME} ({rows} rows), "
          f"{output / SUMMARY_NAME}")
    for k, e in failed.items():
        print(f"  failed: {k} ({e['input']}): {e['error']}", file=sys.stderr)
    if failed:
        sys.exit(1)
    return 0
