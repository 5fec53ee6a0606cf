"""Read STEP parts and assemblies with OpenCascade's XDE: every solid, its name, colour, placement.

The reader walks the XDE assembly tree so that each leaf solid comes with the product name a CAD
user gave it, its colour (sRGB; XDE stores linear RGB) and its placement in the file's frame.
Solids are returned already moved to that placement, so every later stage works in the
assembly frame. A cheap sniff of header and trailer runs first: OpenCascade accepts many broken
files silently (a truncated STEP can still transfer a few solids), and a user deserves to hear
"truncated" rather than get half an assembly.

``write_step`` is the one writer: byte-reproducible STEP files (see its docstring for why that
takes more than a fixed time stamp).
"""

from __future__ import annotations

import io
import logging
import re
from dataclasses import dataclass
from pathlib import Path
from typing import TYPE_CHECKING, Any

import numpy as np
from OCP.IFSelect import IFSelect_RetDone
from OCP.Quantity import Quantity_Color, Quantity_TypeOfColor
from OCP.STEPCAFControl import STEPCAFControl_Reader
from OCP.TCollection import TCollection_AsciiString, TCollection_ExtendedString
from OCP.TDataStd import TDataStd_Name
from OCP.TDF import TDF_Label, TDF_LabelSequence, TDF_Tool
from OCP.TDocStd import TDocStd_Document
from OCP.TopAbs import TopAbs_SOLID
from OCP.TopExp import TopExp_Explorer
from OCP.TopLoc import TopLoc_Location
from OCP.TopoDS import TopoDS, TopoDS_Shape, TopoDS_Solid
from OCP.XCAFDoc import (
    XCAFDoc_ColorTool,
    XCAFDoc_ColorType,
    XCAFDoc_DocumentTool,
    XCAFDoc_ShapeTool,
)

from cadio.errors import StepReadError
from cadio.records import SolidInfo
from cadio.workspace import atomic_path

if TYPE_CHECKING:
    import build123d as bd

log = logging.getLogger(__name__)

_HEADER = b"ISO-10303-21"
_TRAILER = b"END-ISO-10303-21"
_COLOUR_TYPES = (XCAFDoc_ColorType.XCAFDoc_ColorSurf, XCAFDoc_ColorType.XCAFDoc_ColorGen)
_STYLE_BLOCK = re.compile(r"^#(\d+) = MECHANICAL_DESIGN_GEOMETRIC_PRESENTATION_REPRESENTATION",
                          re.MULTILINE)
_ENTITY = re.compile(r"#(\d+) = (.*?);\n", re.DOTALL)
_REF = re.compile(r"#(\d+)")
_OCCURRENCE = re.compile(r"NEXT_ASSEMBLY_USAGE_OCCURRENCE\(\s*'\d+'(.*?\);\n)", re.DOTALL)


@dataclass(frozen=True)
class StepSolid:
    """One solid of a STEP file: its description and the OCP solid, located in the file frame.

    item: the XDE assembly item holding it, as label entries from its root through each
    component ("0:1:1:1", "0:1:1:1:2", ...); subshape: its 1-based index among the solids of
    that item's shape when the shape holds several, else 0. Notes attach there.
    """

    info: SolidInfo
    shape: TopoDS_Solid
    item: tuple[str, ...] = ()
    subshape: int = 0


def sniff_step(path: Path) -> None:
    """Check that ``path`` looks like a complete STEP (ISO 10303-21) file.

    Raises:
        StepReadError: the file is empty, is not STEP, or lacks its closing trailer.
    """
    size = path.stat().st_size
    if size == 0:
        raise StepReadError(path, "empty file")
    with path.open("rb") as fh:
        head = fh.read(256).lstrip(b"\xef\xbb\xbf \t\r\n")
        fh.seek(max(0, size - 4096))
        tail = fh.read()
    if not head.upper().startswith(_HEADER):
        raise StepReadError(path, "not a STEP file (no ISO-10303-21 header)")
    if _TRAILER not in tail.upper():
        raise StepReadError(path, "truncated STEP file (no END-ISO-10303-21 trailer)")


def read_step(path: Path) -> list[StepSolid]:
    """Read every solid of a STEP part or assembly.

    Args:
        path: a ``.step``/``.stp`` file.

    Returns:
        One ``StepSolid`` per leaf solid, in assembly-tree order, indexed from 0, each moved to
        its placement (mm) in the file's frame.

    Raises:
        StepReadError: the file is unreadable, not STEP, truncated, or holds no solid.
    """
    path = Path(path)
    sniff_step(path)
    return step_solids(path, transfer_step(path))


def step_solids(path: Path, doc: TDocStd_Document) -> list[StepSolid]:
    """The solids of a document a STEP file was transferred into, in ``read_step`` order.

    Raises:
        StepReadError: the document holds no solid.
    """
    shape_tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    colour_tool = XCAFDoc_DocumentTool.ColorTool_s(doc.Main())
    roots = TDF_LabelSequence()
    shape_tool.GetFreeShapes(roots)
    walker = _Walker(shape_tool, colour_tool)
    for i in range(1, roots.Length() + 1):
        walker.walk(roots.Value(i), TopLoc_Location(), "", item=(_entry(roots.Value(i)),))
    if not walker.solids:
        raise StepReadError(path, "the file holds no solid (only surfaces, curves or nothing)")
    return walker.solids


def transfer_step(path: Path, doc: TDocStd_Document | None = None) -> TDocStd_Document:
    """Transfer the STEP file into ``doc`` (a new plain document by default): names, colours,
    assembly tree.

    Raises:
        StepReadError: OpenCascade cannot parse or transfer the file.
    """
    doc = doc if doc is not None else TDocStd_Document(TCollection_ExtendedString("XmlOcaf"))
    reader = STEPCAFControl_Reader()
    reader.SetColorMode(True)
    reader.SetNameMode(True)
    status = reader.ReadFile(str(path))
    if status != IFSelect_RetDone:
        raise StepReadError(path, f"OpenCascade could not parse the file ({status.name})")
    if not reader.Transfer(doc):
        raise StepReadError(path, "OpenCascade could not transfer the STEP entities to shapes")
    return doc


class _Walker:
    """Depth-first walk of the XDE tree collecting located leaf solids."""

    def __init__(self, shape_tool: XCAFDoc_ShapeTool, colour_tool: XCAFDoc_ColorTool) -> None:
        self.shape_tool = shape_tool
        self.colour_tool = colour_tool
        self.solids: list[StepSolid] = []

    def walk(self, label: TDF_Label, loc: TopLoc_Location, path: str, colour: str = "",
             item: tuple[str, ...] = ()) -> None:
        name = _name(label)
        colour = _label_colour(label) or colour
        here = f"{path}/{name}" if path else name
        if XCAFDoc_ShapeTool.IsAssembly_s(label):
            comps = TDF_LabelSequence()
            XCAFDoc_ShapeTool.GetComponents_s(label, comps)
            for i in range(1, comps.Length() + 1):
                comp = comps.Value(i)
                ref = TDF_Label()
                XCAFDoc_ShapeTool.GetReferredShape_s(comp, ref)
                comp_loc = loc.Multiplied(XCAFDoc_ShapeTool.GetLocation_s(comp))
                comp_colour = _label_colour(comp) or colour
                self.walk(ref, comp_loc, f"{here}/{_name(comp)}", comp_colour,
                          (*item, _entry(comp)))
            return
        shape = XCAFDoc_ShapeTool.GetShape_s(label)
        self._add_solids(shape, loc, name, here, colour, item)

    def _add_solids(self, shape: TopoDS_Shape, loc: TopLoc_Location, name: str, path: str,
                    colour: str, item: tuple[str, ...]) -> None:
        explorer = TopExp_Explorer(shape, TopAbs_SOLID)
        solids = []
        while explorer.More():
            solids.append(TopoDS.Solid_s(explorer.Current()))
            explorer.Next()
        for k, solid in enumerate(solids):
            own = self._shape_colour(solid) or colour
            label = name if len(solids) == 1 else f"{name}#{k + 1}"
            located = TopoDS.Solid_s(solid.Moved(loc))
            info = SolidInfo(
                index=len(self.solids), name=label or f"solid{len(self.solids)}", colour=own,
                placement=location_matrix(loc), path_in_assembly=path,
            )
            self.solids.append(StepSolid(info=info, shape=located, item=item,
                                         subshape=k + 1 if len(solids) > 1 else 0))

    def _shape_colour(self, shape: TopoDS_Shape) -> str:
        colour = Quantity_Color()
        for kind in _COLOUR_TYPES:
            if self.colour_tool.GetColor(shape, kind, colour):
                return _hex(colour)
        return ""


def _entry(label: TDF_Label) -> str:
    text = TCollection_AsciiString()
    TDF_Tool.Entry_s(label, text)
    return str(text.ToCString())


def _name(label: TDF_Label) -> str:
    attr = TDataStd_Name()
    if label.FindAttribute(TDataStd_Name.GetID_s(), attr):
        return str(attr.Get().ToExtString()).strip()
    return ""


def _label_colour(label: TDF_Label) -> str:
    colour = Quantity_Color()
    for kind in _COLOUR_TYPES:
        if XCAFDoc_ColorTool.GetColor_s(label, kind, colour):
            return _hex(colour)
    return ""


def _hex(colour: Quantity_Color) -> str:
    r, g, b = colour.Values(Quantity_TypeOfColor.Quantity_TOC_sRGB)
    return "#" + "".join(f"{round(min(max(c, 0.0), 1.0) * 255):02x}" for c in (r, g, b))


def location_matrix(loc: TopLoc_Location) -> np.ndarray:
    """The 4 x 4 matrix of a location (its rotation may carry a scale factor)."""
    trsf = loc.Transformation()
    m = np.eye(4)
    for i in range(3):
        for j in range(4):
            m[i, j] = trsf.Value(i + 1, j + 1)
    return m


# --------------------------------------------------------------------------- writing


def write_step(
    shape_or_compound: bd.Shape[Any], path: Path | str, timestamp: str = "2000-01-01T00:00:00"
) -> None:
    """Write a shape (a labelled, coloured compound for an assembly) as byte-reproducible STEP.

    Reproducible bytes keep content hashes stable downstream. A fixed header ``timestamp`` is
    not enough: OCCT writes the colour/style entities in a run-dependent order (a map keyed by
    shape addresses), so they are put in a canonical order before writing; and it numbers the
    assembly occurrences from a counter that lives as long as the process, so they are
    renumbered from 1 in each file. An existing file
    with identical bytes is left untouched (its mtime too); otherwise the write is atomic.

    Args:
        shape_or_compound: a build123d shape; labels and colours of a compound's children
            become product names and colours.
        path: the ``.step`` file to write; missing parent folders are created.
        timestamp: the time stamp written in the STEP header (ISO 8601).
    """
    import build123d as bd  # only the writer pays for build123d; the reader needs OCP alone

    buf = io.BytesIO()
    bd.export_step(shape_or_compound, buf, timestamp=timestamp)
    text = _canonical_occurrences(_canonical_styles(buf.getvalue().decode("latin-1")))
    data = text.encode("latin-1")
    path = Path(path)
    if path.is_file() and path.read_bytes() == data:
        return
    with atomic_path(path) as tmp:
        tmp.write_bytes(data)


def _canonical_styles(step: str) -> str:
    """Renumber OCCT's colour section in a fixed order.

    OCCT writes one block of presentation entities per coloured shape at the end of DATA, in
    the iteration order of a map keyed by shape addresses, so the block order (and with it
    the entity numbers) changes from run to run. Each block only refers to itself and to
    earlier (deterministic) entities; sorting the blocks by their content with internal
    references made relative gives the same bytes every time. A file that does not have
    this shape is returned unchanged (and the determinism test would catch it).
    """
    first = _STYLE_BLOCK.search(step)
    end = step.rfind("ENDSEC;")
    if first is None or end < first.start():
        return step
    start_id, prefix = int(first.group(1)), step[:first.start()]
    if any(int(ref) >= start_id for ref in _REF.findall(prefix)):
        return step
    blocks = _style_blocks(step[first.start():end])
    if blocks is None:
        return step
    blocks.sort(key=lambda block: _renumbered(block, start_id, relative=True))
    out, next_id = [], start_id
    for block in blocks:
        out.append(_renumbered(block, next_id, relative=False))
        next_id += len(block)
    return prefix + "".join(out) + step[end:]


def _canonical_occurrences(step: str) -> str:
    """Number the ids of NEXT_ASSEMBLY_USAGE_OCCURRENCE entities 1, 2, ... in file order.

    OCCT takes them from a process-wide counter, so the same assembly written after another
    one would get other ids (and another content hash). The ids are labels: no entity refers
    to them.
    """
    counter = iter(range(1, 1 << 30))

    def renumbered(m: re.Match[str]) -> str:
        # OCCT wraps a line near 80 characters, so the old id's width moved the break: the
        # entity is written on one line, the same whatever the counter said.
        parts = m.group(1)[:-1].split("'")  # even items lie outside the quoted names
        rest = "'".join(re.sub(r"\n\s*", "", p) if i % 2 == 0 else p
                        for i, p in enumerate(parts)) + "\n"
        return f"NEXT_ASSEMBLY_USAGE_OCCURRENCE('{next(counter)}'{rest}"

    return _OCCURRENCE.sub(renumbered, step)


def _style_blocks(tail: str) -> list[list[tuple[int, str]]] | None:
    """Entities (id, text on one line) grouped in blocks; None if a block refers outside."""
    blocks: list[list[tuple[int, str]]] = []
    for m in _ENTITY.finditer(tail):
        text = re.sub(r"\s*\n\s*", "", m.group(2))
        if text.startswith("MECHANICAL_DESIGN_GEOMETRIC_PRESENTATION_REPRESENTATION"):
            blocks.append([])
        blocks[-1].append((int(m.group(1)), text))
    start_id = blocks[0][0][0]
    for block in blocks:
        own = {ident for ident, _ in block}
        refs = {int(r) for _, text in block for r in _REF.findall(text)}
        if any(r >= start_id and r not in own for r in refs):
            return None
    return blocks


def _renumbered(block: list[tuple[int, str]], first_id: int, relative: bool) -> str:
    """The block's entities numbered from ``first_id`` (or as ``@k`` offsets if relative)."""
    mapping = {old: k for k, (old, _) in enumerate(block)}

    def ref(m: re.Match[str]) -> str:
        k = mapping.get(int(m.group(1)))
        if k is None:
            return m.group(0)
        return f"@{k}" if relative else f"#{first_id + k}"

    return "".join(f"{_REF.sub(ref, f'#{old} = {text}')};\n" for old, text in block)
