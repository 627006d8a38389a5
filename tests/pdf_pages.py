"""A PDF as a reader sees it: page sizes, every word with its box (poppler's ``pdftotext
-bbox``), and the pages rendered to PNG (``pdftoppm``). ``make test`` installs poppler-utils."""

from __future__ import annotations

import html
import re
import shutil
import subprocess
from dataclasses import dataclass
from itertools import combinations
from pathlib import Path

A4_PT = (595.44, 841.68)  # 8.27 x 11.69 in, as matplotlib writes A4


def require_poppler() -> None:
    missing = [t for t in ("pdftotext", "pdftoppm") if shutil.which(t) is None]
    assert not missing, (
        f"{', '.join(missing)} not found: apt-get install -y poppler-utils (make test does)"
    )


@dataclass(frozen=True)
class Word:
    x0: float
    y0: float  # from the top of the page, in points
    x1: float
    y1: float
    text: str


@dataclass(frozen=True)
class Page:
    width: float
    height: float
    words: list[Word]

    def text(self) -> str:
        return " ".join(w.text for w in self.words)


def pages(pdf: Path) -> list[Page]:
    require_poppler()
    out = subprocess.run(["pdftotext", "-bbox", str(pdf), "-"], capture_output=True,
                         text=True, check=True, timeout=120).stdout
    found = []
    for w, h, body in re.findall(
        r'<page width="([\d.]+)" height="([\d.]+)">(.*?)</page>', out, re.S
    ):
        words = [
            Word(float(a), float(b), float(c), float(d), html.unescape(t))
            for a, b, c, d, t in re.findall(
                r'<word xMin="([\d.-]+)" yMin="([\d.-]+)" xMax="([\d.-]+)" '
                r'yMax="([\d.-]+)">(.*?)</word>', body)
        ]
        found.append(Page(float(w), float(h), words))
    return found


def overlapping_words(page: Page, tolerance_pt: float = 0.5) -> list[tuple[Word, Word]]:
    """Pairs of words whose boxes overlap by more than ``tolerance_pt`` both ways."""
    bad = []
    for a, b in combinations(page.words, 2):
        dx = min(a.x1, b.x1) - max(a.x0, b.x0)
        dy = min(a.y1, b.y1) - max(a.y0, b.y0)
        if dx > tolerance_pt and dy > tolerance_pt:
            bad.append((a, b))
    return bad


def words_off_the_page(page: Page, margin_pt: float = 0.0) -> list[Word]:
    return [w for w in page.words if w.x0 < margin_pt or w.y0 < margin_pt
            or w.x1 > page.width - margin_pt or w.y1 > page.height - margin_pt]


def render_png(pdf: Path, out_dir: Path, dpi: int = 50) -> list[Path]:
    """Each page as ``out_dir/page-N.png`` at ``dpi``."""
    require_poppler()
    subprocess.run(["pdftoppm", "-r", str(dpi), "-png", str(pdf), str(out_dir / "page")],
                   check=True, timeout=120)
    return sorted(out_dir.glob("page-*.png"), key=lambda p: int(p.stem.rsplit("-", 1)[1]))
