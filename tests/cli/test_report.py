"""The HTML report of a demo run: images present and relative, tables, charts, escaping."""

from __future__ import annotations

from html.parser import HTMLParser
from pathlib import Path
from typing import Any
from urllib.parse import unquote

import numpy as np
import pytest
from PIL import Image

from regnf.cli.report import write_report

SECTION_IMAGES = ["renders/scene/contact_sheet.png", "renders/composite/view 0.png",
                  "completion/c_1.png"]


class _PageParser(HTMLParser):
    """Collects image sources and the registration table's headers and rows."""

    def __init__(self) -> None:
        super().__init__()
        self.img_src: list[str] = []
        self.img_alt: list[str] = []
        self.headers: list[str] = []
        self.rows: list[list[tuple[str, str]]] = []
        self._in_table = False
        self._cell: tuple[str, list[str]] | None = None

    def handle_starttag(self, tag: str, attrs: list[tuple[str, str | None]]) -> None:
        a = dict(attrs)
        if tag == "img":
            self.img_src.append(a["src"] or "")
            self.img_alt.append(a.get("alt") or "")
        elif tag == "table":
            self._in_table = a.get("id") == "registration-table"
        elif self._in_table and tag == "tr":
            self.rows.append([])
        elif self._in_table and tag in ("td", "th"):
            self._cell = (tag, [a.get("class") or ""])

    def handle_data(self, data: str) -> None:
        if self._cell is not None:
            self._cell[1].append(data)

    def handle_endtag(self, tag: str) -> None:
        if tag == "table":
            self._in_table = False
        elif self._cell is not None and tag in ("td", "th"):
            kind, (cls, *text) = self._cell
            if kind == "th":
                self.headers.append("".join(text))
            else:
                self.rows[-1].append((cls, "".join(text)))
            self._cell = None


def _parse(path: Path) -> _PageParser:
    parser = _PageParser()
    parser.feed(path.read_text(encoding="utf-8"))
    parser.close()
    parser.rows = [row for row in parser.rows if row]
    return parser


def _png(path: Path, colour: int = 128) -> None:
    path.parent.mkdir(parents=True, exist_ok=True)
    Image.fromarray(np.full((8, 12, 3), colour, np.uint8)).save(path)


def _history(n: int, start: float, s_end: float) -> list[dict[str, float]]:
    return [{"iteration": i, "loss": start * 0.8 ** i, "mean_residual_A": 0.01,
             "mean_residual_B": 0.012, "alpha": 2.0, "c": 0.01, "s": 1.0 + (s_end - 1.0) * i / n}
            for i in range(n)]


def _summary(out: Path) -> dict[str, Any]:
    for i, rel in enumerate(SECTION_IMAGES):
        _png(out / rel, 40 * i)
    (out / "stage").mkdir(parents=True, exist_ok=True)
    (out / "stage" / "ac-room.usda").write_text("#usda 1.0\n")
    (out / "ac-room.usdz").write_bytes(b"PK")
    return {
        "title": "regnf demo: ac-room",
        "command": "regnf demo --out out/demo",
        "created": "2026-11-22T07:00:00Z",
        "machine": {"cpu_count": 2, "device": "cpu", "torch": "2.13.0+cpu", "python": "3.11.4",
                    "platform": "Linux-test"},
        "total_seconds": 612.3,
        "steps": [
            {"name": "capture room", "seconds": 0.8, "cached": False, "detail": "30 RGB-D frames"},
            {"name": "train fields", "seconds": 400.0, "cached": True, "detail": "3 objects"},
            {"name": "register", "seconds": 15.5, "cached": False, "detail": ""},
        ],
        "registrations": [
            {"instance": "c_1", "object": "c", "label": "chair", "accepted": True,
             "confidence": 0.91, "rot_geodesic_rad": 0.0012, "trans_m": 0.003,
             "trans_rel_diag": 0.0021, "scale_rel": 0.0015, "seconds": 5.2,
             "history": _history(20, 0.52, 1.02)},
            {"instance": "t_1", "object": "t", "label": "table", "accepted": False,
             "confidence": 0.4, "rot_geodesic_rad": 0.05, "trans_m": 0.03,
             "trans_rel_diag": 0.02, "scale_rel": 0.004, "seconds": 7.0,
             "history": _history(15, 0.8, 0.97)},
            {"instance": "s_1", "object": "s", "label": "sofa", "accepted": True,
             "confidence": 0.8, "rot_geodesic_rad": 0.002, "trans_m": 0.004,
             "trans_rel_diag": 0.002, "scale_rel": 0.03, "seconds": 6.0, "history": []},
        ],
        "thresholds": {"rot_geodesic_rad": 0.02, "trans_rel_diag": 0.01, "scale_rel": 0.01},
        "sections": [
            {"title": "Object completion", "text": "Fields completed by the library.",
             "images": [{"path": SECTION_IMAGES[0], "caption": "scene field alone"},
                        {"path": SECTION_IMAGES[2], "caption": "chair completed"}]},
            {"title": "Composite", "text": "The edited room.",
             "images": [{"path": SECTION_IMAGES[1], "caption": "view 0"}]},
        ],
        "files": [{"path": "stage/ac-room.usda", "what": "the USD stage"},
                  {"path": "ac-room.usdz", "what": "the packaged stage"}],
    }


def test_full_summary_gives_a_complete_report(tmp_path: Path) -> None:
    summary = _summary(tmp_path)
    path = write_report(tmp_path, summary)
    assert path == tmp_path / "report.html"
    page = _parse(path)

    sources = [unquote(src) for src in page.img_src]
    assert sources, "no images in the report"
    for src in sources:
        assert not Path(src).is_absolute()
        assert (tmp_path / src).is_file(), src
    assert set(SECTION_IMAGES) <= set(sources)
    for name in ("loss_curves.png", "timings.png"):
        assert f"report/{name}" in sources
        with Image.open(tmp_path / "report" / name) as im:
            im.verify()
    assert not list(tmp_path.rglob(".*")), "temporary files left behind"

    text = path.read_text(encoding="utf-8")
    for heading in ("Timings", "Registration against ground truth", "Loss curves",
                    "Object completion", "Composite", "Files"):
        assert f">{heading}</h2>" in text
    assert 'href="stage/ac-room.usda"' in text and 'href="ac-room.usdz"' in text
    assert "http://" not in text and "https://" not in text and "<script" not in text

    # One row per registration plus the median row.
    assert len(page.rows) == len(summary["registrations"]) + 1
    assert page.rows[-1][0][1] == "median"
    rad = page.headers.index("rotation (rad)")
    scale = page.headers.index("scale (%)")
    rows = {row[0][1]: row for row in page.rows}
    assert "bad" in rows["t_1"][rad][0].split()  # 0.05 rad > 0.02
    assert "bad" not in rows["c_1"][rad][0].split()  # 0.0012 rad <= 0.02
    assert "bad" in rows["s_1"][scale][0].split()  # 3 % > 1 %
    assert "bad" not in rows["t_1"][scale][0].split()  # 0.4 % <= 1 %
    assert float(rows["t_1"][page.headers.index("rotation (°)")][1]) == pytest.approx(2.865, 1e-3)
    assert float(rows["median"][rad][1]) == pytest.approx(0.002)


def test_missing_image_raises_and_writes_nothing(tmp_path: Path) -> None:
    summary = _summary(tmp_path)
    (tmp_path / SECTION_IMAGES[1]).unlink()
    with pytest.raises(FileNotFoundError, match="view 0.png"):
        write_report(tmp_path, summary)
    assert not (tmp_path / "report.html").exists()
    assert not (tmp_path / "report").exists()


def test_missing_listed_file_raises(tmp_path: Path) -> None:
    summary = _summary(tmp_path)
    (tmp_path / "ac-room.usdz").unlink()
    with pytest.raises(FileNotFoundError, match="ac-room.usdz"):
        write_report(tmp_path, summary)
    assert not (tmp_path / "report.html").exists()


def test_absolute_path_is_refused(tmp_path: Path) -> None:
    summary = _summary(tmp_path)
    summary["files"].append({"path": str(tmp_path / "ac-room.usdz"), "what": "absolute"})
    with pytest.raises(ValueError, match="relative"):
        write_report(tmp_path, summary)
    assert not (tmp_path / "report.html").exists()


def test_summary_text_is_escaped(tmp_path: Path) -> None:
    summary = _summary(tmp_path)
    evil = "<script>alert('x')</script>"
    summary["sections"][0]["images"][0]["caption"] = evil
    summary["sections"][0]["text"] = f"a & b {evil}"
    summary["title"] = f"demo {evil}"
    summary["registrations"][0]["instance"] = '"c_1"><b>'
    summary["registration_note"] = f"1 of 3 rejected {evil}"
    path = write_report(tmp_path, summary)
    text = path.read_text(encoding="utf-8")
    assert "<script" not in text and "<b>" not in text
    assert "&lt;script&gt;alert(&#39;x&#39;)&lt;/script&gt;" in text
    assert "a &amp; b" in text
    assert "1 of 3 rejected &lt;script&gt;" in text
    page = _parse(path)
    assert evil in page.img_alt
    assert '"c_1"><b>' in [row[0][1] for row in page.rows]


def test_empty_histories_give_no_loss_chart(tmp_path: Path) -> None:
    summary = _summary(tmp_path)
    for reg in summary["registrations"]:
        reg["history"] = []
    _png(tmp_path / "report" / "loss_curves.png")  # left over from an earlier run
    path = write_report(tmp_path, summary)
    assert path.is_file()
    assert not (tmp_path / "report" / "loss_curves.png").exists()
    assert (tmp_path / "report" / "timings.png").is_file()
    text = path.read_text(encoding="utf-8")
    assert "no refinement history" in text.lower()
    assert "loss_curves.png" not in text


def test_minimal_summary(tmp_path: Path) -> None:
    path = write_report(tmp_path, {"title": "empty run"})
    text = path.read_text(encoding="utf-8")
    assert "<title>empty run</title>" in text
    assert not (tmp_path / "report").exists()
    assert _parse(path).img_src == []
