"""Several sources into one scan, for ``pfnet prepare SRC1 SRC2 ...``."""

from __future__ import annotations

from dataclasses import replace
from pathlib import Path

from pfnet.data.sources import Scan, ShapeItem, unique_names
from pfnet.errors import ConfigError, DataError

__all__ = ["Y_UP", "merge_scans", "several_manifest", "several_sources"]

# Sources whose shapes are y-up as they come (the AC3D trees are y-up in their files).
Y_UP = ("sweethome3d", "procedural", "sweethome3d-app", "flightgear", "torcs", "crrcsim")


def merge_scans(scans: list[tuple[str, Path, Scan]]) -> tuple[Scan, dict[str, dict]]:
    """One scan of several sources, and each shape's origin (source format, path, licence).

    Names are made unique across the sources (a clash gets ``-2``...); every shape is
    credited (sources without per-model credits under their own licence record).

    Raises:
        DataError: Two sources hold a shape of the same key (the same source twice?).
    """
    items: list[ShapeItem] = []
    licenses: list[dict] = []
    dropped: dict[str, int] = {}
    skipped: list[tuple[str, str]] = []
    credits: dict[str, tuple[str, str]] = {}
    origins: dict[str, dict] = {}
    for fmt, path, scan in scans:
        records = list(scan.licenses) or [
            {"source": str(path), "catalogue": str(path), "license": "as given by the user"}
        ]
        licenses += [r for r in records if r not in licenses]
        by_source = {r["source"]: r for r in records}
        for item in scan.items:
            if item.key in origins:
                raise DataError(f"{path}: shape {item.key} is also in another source")
            record_source, creator = scan.credits.get(item.key, (records[0]["source"], ""))
            credits[item.key] = (record_source, creator)
            record = by_source.get(record_source, records[0])
            origins[item.key] = {
                "source": fmt,
                "path": item.path,
                "license": record.get("license", ""),
            }
            items.append(item)
        for reason, n in scan.dropped.items():
            dropped[f"{fmt}: {reason}"] = dropped.get(f"{fmt}: {reason}", 0) + n
        skipped += scan.skipped
    names = unique_names({item.key: item.name for item in items})
    items = [replace(item, name=names[item.key]) for item in items]
    merged = Scan(items=items, licenses=licenses, dropped=dropped, skipped=skipped, credits=credits)
    return merged, origins


def several_sources(source, format: str, benchmark_formats) -> tuple:
    """``(source, sources, formats, format name)``: a list of one source is that source; a
    list of several gives their paths and formats (each detected unless ``format`` names one).

    Raises:
        ConfigError: An empty list, or a benchmark or procedural source among several.
    """
    from pfnet.data.sources.registry import detect_format

    if isinstance(source, (list, tuple)) and not source:
        raise ConfigError("no source given")
    if isinstance(source, (list, tuple)) and len(source) == 1:
        source = source[0]
    if not isinstance(source, (list, tuple)):
        return source, None, None, detect_format(source) if format == "auto" else format
    sources = [Path(s) for s in source]
    formats = [detect_format(s) if format == "auto" else format for s in sources]
    unfit = sorted({f for f in formats if f in benchmark_formats or f == "procedural"})
    if unfit:
        raise ConfigError(
            f"several sources take mesh and catalogue sources only, not {', '.join(unfit)}"
        )
    return None, sources, formats, ", ".join(dict.fromkeys(formats))


def several_manifest(
    manifest: dict,
    formats: list[str],
    sources: list[Path] | None,
    distinct_info: dict,
    origins: dict[str, dict],
    kept: dict[str, list],
) -> None:
    """Add to ``manifest`` the sources, the up axis, the distinct step's record and each
    shape's origin (source format, original path, licence)."""
    if sources is not None:
        manifest["source"] = {
            "format": "several",
            "sources": [
                {"format": f, "path": str(s)} for f, s in zip(formats, sources, strict=True)
            ],
        }
    if all(f in Y_UP for f in formats):
        manifest["up_axis"] = "y"
    if distinct_info:
        manifest["distinct"] = distinct_info
    if origins:
        manifest["shapes"] = {
            item.name: origins[item.key]
            for split in sorted(kept)
            for item, _ in sorted(kept[split], key=lambda s: s[0].name)
        }
