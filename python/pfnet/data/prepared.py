"""What ``pfnet prepare`` wrote (:class:`PrepareReport`), for every source: meshes and clouds
(:func:`pfnet.data.prepare.prepare_dataset`), the benchmarks (:mod:`pfnet.data.benchmarks`)
and KITTI (:mod:`pfnet.data.kitti`)."""

from __future__ import annotations

from dataclasses import dataclass, field
from pathlib import Path

from pfnet.data.categories import category_title
from pfnet.data.distinct import distinct_summary
from pfnet.data.format import SPLITS

__all__ = ["PrepareReport"]

SKIPPED_SHOWN = 20  # skipped files the summary names; the manifest keeps more


@dataclass
class PrepareReport:
    """What :func:`prepare_dataset` wrote.

    Attributes:
        out: The dataset folder.
        format: The source format.
        counts: ``{split: {category: shapes}}``.
        skipped: ``(path, reason)`` of every shape that could not be prepared.
        dropped: Shapes left out on purpose, by reason (e.g. ``unmatched``, ``light_source``).
        seconds: Wall time.
        manifest: The manifest written.
        distinct: The manifest's ``distinct`` record (:func:`pfnet.data.distinct.split_distinct`).
    """

    out: Path
    format: str
    counts: dict[str, dict[str, int]]
    skipped: list[tuple[str, str]] = field(default_factory=list)
    dropped: dict[str, int] = field(default_factory=dict)
    seconds: float = 0.0
    manifest: dict = field(default_factory=dict)
    distinct: dict = field(default_factory=dict)

    @property
    def total(self) -> int:
        """Shapes written, all splits together."""
        return sum(sum(c.values()) for c in self.counts.values())

    def summary(self) -> str:
        """A short human-readable table: shapes per category and split, skipped and dropped."""
        categories = sorted({c for counts in self.counts.values() for c in counts})
        titles = {c: category_title(c) for c in categories} | {"total": "total"}
        width = max([len(t) for t in titles.values()] + [8])
        lines = [
            f"wrote {self.out}: {self.total} shapes from {self.format} in {self.seconds:.1f} s",
            f"{'category':<{width}} " + " ".join(f"{s:>6}" for s in (*SPLITS, "total")),
        ]
        for category in [*categories, "total"]:
            row = [
                sum(self.counts[s].values())
                if category == "total"
                else self.counts[s].get(category, 0)
                for s in SPLITS
            ]
            cells = " ".join(f"{n:>6}" for n in (*row, sum(row)))
            lines.append(f"{titles[category]:<{width}} {cells}")
        for reason, count in sorted(self.dropped.items()):
            if count:
                hint = " (categories 'all' keeps them)" if reason == "unmatched" else ""
                lines.append(f"dropped {count} shapes: {reason.replace('_', ' ')}{hint}")
        lines += distinct_summary(self.distinct)
        if self.skipped:
            lines.append(f"skipped {len(self.skipped)} files:")
            shown = self.skipped[:SKIPPED_SHOWN]
            lines += [f"  {path[:300]}: {reason[:300]}" for path, reason in shown]
            if len(self.skipped) > len(shown):
                lines.append(f"  … and {len(self.skipped) - len(shown)} more")
        return "\n".join(lines)
