"""Read STEP parts and assemblies with OpenCascade's XDE: every solid, its name, colour, placement.

The reader walks the XDE assembly tree so that each leaf solid comes with the product name a CAD
user gave it, its colour (sRGB; XDE stores linear RGB) and its placement in the file's frame.
Solids are returned already moved to that placement, so every later stage works in the
assembly frame. A cheap sniff of header and trailer runs first: OpenCascade accepts many broken
files silently (a truncated STEP can still transfer a few solids), and a user deserves to hear
"truncated" rather than get half an assembly.
"""

from __future__ import annotations

import logging
from dataclasses import dataclass
from pathlib import Path

import numpy as np
from OCP.IFSelect import IFSelect_RetDone
from OCP.Quantity import Quantity_Color, Quantity_TypeOfColor
from OCP.STEPCAFControl import STEPCAFControl_Reader
from OCP.TCollection import TCollection_ExtendedString
from OCP.TDataStd import TDataStd_Name
from OCP.TDF import TDF_Label, TDF_LabelSequence
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

log = logging.getLogger(__name__)

STEP_SUFFIXES = (".step", ".stp")
_HEADER = b"ISO-10303-21"
_TRAILER = b"END-ISO-10303-21"
_COLOUR_TYPES = (XCAFDoc_ColorType.XCAFDoc_ColorSurf, XCAFDoc_ColorType.XCAFDoc_ColorGen)


@dataclass(frozen=True)
class StepSolid:
    """One solid of a STEP file: its description and the OCP solid, located in the file frame."""

    info: SolidInfo
    shape: TopoDS_Solid


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
    doc = _transfer(path)
    shape_tool = XCAFDoc_DocumentTool.ShapeTool_s(doc.Main())
    colour_tool = XCAFDoc_DocumentTool.ColorTool_s(doc.Main())
    roots = TDF_LabelSequence()
    shape_tool.GetFreeShapes(roots)
    walker = _Walker(shape_tool, colour_tool)
    for i in range(1, roots.Length() + 1):
        walker.walk(roots.Value(i), TopLoc_Location(), "")
    if not walker.solids:
        raise StepReadError(path, "the file holds no solid (only surfaces, curves or nothing)")
    return walker.solids


def _transfer(path: Path) -> TDocStd_Document:
    doc = TDocStd_Document(TCollection_ExtendedString("XmlOcaf"))
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

    def walk(self, label: TDF_Label, loc: TopLoc_Location, path: str, colour: str = "") -> None:
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
                self.walk(ref, comp_loc, f"{here}/{_name(comp)}", comp_colour)
            return
        shape = XCAFDoc_ShapeTool.GetShape_s(label)
        self._add_solids(shape, loc, name, here, colour)

    def _add_solids(
        self, shape: TopoDS_Shape, loc: TopLoc_Location, name: str, path: str, colour: str
    ) -> None:
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
                placement=_matrix(loc), path_in_assembly=path,
            )
            self.solids.append(StepSolid(info=info, shape=located))

    def _shape_colour(self, shape: TopoDS_Shape) -> str:
        colour = Quantity_Color()
        for kind in _COLOUR_TYPES:
            if self.colour_tool.GetColor(shape, kind, colour):
                return _hex(colour)
        return ""


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


def _matrix(loc: TopLoc_Location) -> np.ndarray:
    trsf = loc.Transformation()
    m = np.eye(4)
    for i in range(3):
        for j in range(4):
            m[i, j] = trsf.Value(i + 1, j + 1)
    return m
