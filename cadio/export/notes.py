"""The assembly as an XDE document (XBF) with the predictions attached as OCCT notes.

The STEP file is transferred into a binary XDE document (names, colours and the assembly tree
as the file has them) and ``XCAFDoc_NotesTool`` comments are attached:

- one note per part, on the part's assembly item (the path of component labels from its root;
  for the k-th solid of a shape holding several solids, on that sub-shape), with the pairs it
  belongs to;
- one note per pair, attached to the items of both parts;
- one note for the assembly (status, agreement, models), on each root.

Each comment's text is a JSON object (``kind``: part, pair or assembly, and a one-line
``summary`` for people). XBF is the format that keeps them: the XML format overwrites the
comment text with its time stamp and STEP export drops notes (OCCT behaviour). Reopen a
saved document with ``read_notes`` (``Retrieve``: ``Open`` leaves it empty).

OpenCascade takes a "|" in a path for a separator of its own (it cannot save to or retrieve
from ``exports/a|b/``), and folder and file names come from the assembly's file name: documents
are saved and retrieved in a temporary folder of plain name and copied from or to their place.
"""

from __future__ import annotations

import json
import shutil
import tempfile
from collections import defaultdict
from collections.abc import Iterator
from contextlib import contextmanager
from dataclasses import dataclass
from pathlib import Path
from typing import Any

from OCP.BinXCAFDrivers import BinXCAFDrivers
from OCP.PCDM import PCDM_StoreStatus
from OCP.TCollection import TCollection_AsciiString, TCollection_ExtendedString
from OCP.TColStd import TColStd_ListOfAsciiString
from OCP.TDF import TDF_Label, TDF_LabelSequence, TDF_Tool
from OCP.TDocStd import TDocStd_Document
from OCP.XCAFApp import XCAFApp_Application
from OCP.XCAFDoc import (
    XCAFDoc_AssemblyItemId,
    XCAFDoc_AssemblyItemRef,
    XCAFDoc_DocumentTool,
    XCAFDoc_NoteComment,
    XCAFDoc_NotesTool,
)

from cadio.cad.step import StepSolid, sniff_step, step_solids, transfer_step
from cadio.errors import StepReadError
from cadio.export.predictions import AssemblyMates, PairMates, PartRef, finite
from cadio.workspace import atomic_path

FORMAT = "BinXCAF"
USER = "mateqa"
_FORMATS: set[int] = set()


@dataclass(frozen=True)
class Note:
    """A note read back: its JSON text, author, time stamp and the items it is attached to
    (item path as OCCT writes it, "entry/entry/...", and the sub-shape index or 0)."""

    text: str
    user: str
    timestamp: str
    items: tuple[tuple[str, int], ...]

    @property
    def data(self) -> dict[str, Any]:
        value: dict[str, Any] = json.loads(self.text)
        return value


def _application() -> XCAFApp_Application:
    app = XCAFApp_Application.GetApplication_s()
    if id(app) not in _FORMATS:  # the drivers are registered once per process
        BinXCAFDrivers.DefineFormat_s(app)
        _FORMATS.add(id(app))
    return app


@contextmanager
def _plain_path() -> Iterator[Path]:
    """A path in a fresh temporary folder, named so that OpenCascade reads it as written."""
    with tempfile.TemporaryDirectory(prefix="mateqa-xbf-") as folder:
        yield Path(folder) / "document.xbf"


def _text(value: str) -> TCollection_ExtendedString:
    return TCollection_ExtendedString(value, True)  # UTF-8: part names may hold any script


def _item(solid: StepSolid) -> XCAFDoc_AssemblyItemId:
    path = TColStd_ListOfAsciiString()
    for entry in solid.item:
        path.Append(TCollection_AsciiString(entry))
    return XCAFDoc_AssemblyItemId(path)


def _rel_summary(pair: PairMates) -> str:
    held = [c.relation for c in pair.relations if c.predicted]
    return ", ".join(held) or "no relation"


def part_note(part: PartRef, mates: AssemblyMates) -> dict[str, Any]:
    """The note of one part: its name and the pairs it is in, with their predicted joints."""
    mine = [p for p in mates.pairs if part.index in (p.a.index, p.b.index)]
    pairs = [{"other": (p.b if p.a.index == part.index else p.a).name,
              "other_index": (p.b if p.a.index == part.index else p.a).index,
              "status": p.status, "joint": p.joint.predicted,
              "confidence": finite(p.joint.confidence), "cad_joint": p.joint.cad_kinematic,
              "relations": [c.relation for c in p.relations if c.predicted]} for p in mine]
    joints = [f"{q['joint']} with {q['other']}" for q in pairs if q["joint"] not in (None, "none")]
    return {"kind": "part", "assembly": mates.assembly, "run_id": mates.run_id,
            "part": {"index": part.index, "name": part.name, "path": part.path},
            "summary": f"{part.name}: " + ("; ".join(joints) or "no predicted joint"),
            "pairs": pairs}


def pair_note(pair: PairMates, mates: AssemblyMates) -> dict[str, Any]:
    """The note of one pair: predicted relations and joint beside the CAD's."""
    j = pair.joint
    summary = (f"{pair.a.name} / {pair.b.name}: not captured" if pair.status != "predicted" else
               f"{pair.a.name} / {pair.b.name}: {j.predicted} "
               f"(CAD {j.cad_kinematic}); {_rel_summary(pair)}")
    return {"kind": "pair", "assembly": mates.assembly, "run_id": mates.run_id,
            "a": {"index": pair.a.index, "name": pair.a.name},
            "b": {"index": pair.b.index, "name": pair.b.name},
            "status": pair.status, "views": pair.views, "summary": summary,
            "joint": {"predicted": j.predicted, "confidence": finite(j.confidence),
                      **j.cad_names(), "cad_kinematic": j.cad_kinematic,
                      "cad_suggested": j.cad_suggested, "agrees": j.agrees},
            "relations": [{"relation": c.relation, "predicted": c.predicted,
                           "confidence": finite(c.confidence), "cad": c.cad, "agrees": c.agrees}
                          for c in pair.relations],
            "as_built": [{"relation": m.relation, "face_a": m.face_a, "face_b": m.face_b,
                          "status": m.status, "check": m.text()}
                         for m in mates.as_built
                         if (m.index_a, m.index_b) in ((pair.a.index, pair.b.index),
                                                       (pair.b.index, pair.a.index))]}


def assembly_note(mates: AssemblyMates) -> dict[str, Any]:
    """The note of the assembly: status, agreement with the CAD, models."""
    agreement = mates.agreement()
    acc = agreement["relation_accuracy"]
    built = mates.as_built_verdict()
    summary = (f"{mates.assembly}: {mates.status}" + (f" ({mates.reason})" if mates.reason else "")
               + (f", relation accuracy {acc:.3f} against the CAD" if acc is not None else "")
               + (f"; as built: {built}" if built else ""))
    return {"kind": "assembly", "assembly": mates.assembly, "run_id": mates.run_id,
            "status": mates.status, "reason": mates.reason, "summary": summary,
            "models": dict(mates.models), "agreement": agreement, "as_built": built}


def write_xbf(step: Path, mates: AssemblyMates, out: Path,
              timestamp: str) -> tuple[int, list[StepSolid]]:
    """Write the assembly of ``step`` as an XBF document with the notes; the number of notes
    and the file's solids (``read_step``'s, for the caller that needs their geometry).

    Raises:
        StepReadError: the STEP file cannot be read, or its solids are not the parts of
            ``mates`` (the file changed since the run).
        OSError: the document cannot be saved.
    """
    sniff_step(step)
    app = _application()
    doc = TDocStd_Document(_text(FORMAT))
    app.NewDocument(_text(FORMAT), doc)
    try:
        solids = step_solids(step, transfer_step(step, doc))
        by_index = {s.info.index: s for s in solids}
        for part in mates.parts:
            solid = by_index.get(part.index)
            if solid is None or solid.info.name != part.name:
                raise StepReadError(step, f"solid {part.index} is not the part {part.name!r} "
                                          "of the run (the file changed since?)")
        tool = XCAFDoc_DocumentTool.NotesTool_s(doc.Main())
        count = 0

        def attach(data: dict[str, Any], targets: list[StepSolid]) -> None:
            nonlocal count
            note = tool.CreateComment(_text(USER), _text(timestamp),
                                      _text(json.dumps(data, ensure_ascii=False)))
            for solid in targets:
                if solid.subshape:
                    tool.AddNoteToSubshape(note.Label(), _item(solid), solid.subshape)
                else:
                    tool.AddNote(note.Label(), _item(solid))
            count += 1

        for part in mates.parts:
            attach(part_note(part, mates), [by_index[part.index]])
        for pair in mates.pairs:
            attach(pair_note(pair, mates), [by_index[pair.a.index], by_index[pair.b.index]])
        roots = list({s.item[0]: StepSolid(s.info, s.shape, item=s.item[:1])
                      for s in solids}.values())
        attach(assembly_note(mates), roots)
        out.parent.mkdir(parents=True, exist_ok=True)
        with atomic_path(out) as tmp, _plain_path() as plain:
            status = app.SaveAs(doc, _text(str(plain)))
            if status != PCDM_StoreStatus.PCDM_SS_OK:
                raise OSError(f"{out}: OpenCascade could not save the document ({status.name})")
            shutil.copyfile(plain, tmp)
        return count, solids
    finally:
        if doc.IsOpened():  # saving opens it in the application; a failure before does not
            app.Close(doc)


def _entry(label: TDF_Label) -> str:
    text = TCollection_AsciiString()
    TDF_Tool.Entry_s(label, text)
    return str(text.ToCString())


def read_notes(path: Path) -> list[Note]:
    """Every note of a saved XBF document with the items it is attached to.

    Raises:
        OSError: the file is missing or not an XDE document OpenCascade can retrieve.
    """
    path = Path(path).resolve()
    if not path.is_file():
        raise OSError(f"{path}: no such document")
    app = _application()
    with _plain_path() as plain:
        shutil.copyfile(path, plain)
        try:
            doc = app.Retrieve(_text(str(plain.parent)), _text(plain.name))
        except Exception as exc:  # OCCT raises its own Standard_Failure types
            raise OSError(f"{path}: OpenCascade could not retrieve the document ({exc})") \
                from exc
    try:
        tool: XCAFDoc_NotesTool = XCAFDoc_DocumentTool.NotesTool_s(doc.Main())
        attached: dict[str, list[tuple[str, int]]] = defaultdict(list)
        items = TDF_LabelSequence()
        tool.GetAnnotatedItems(items)
        for i in range(1, items.Length() + 1):
            ref = XCAFDoc_AssemblyItemRef.Get_s(items.Value(i))
            item = ref.GetItem()
            sub = int(ref.GetSubshapeIndex()) if ref.IsSubshapeIndex() else 0
            found = TDF_LabelSequence()
            if sub:
                tool.GetSubshapeNotes(item, sub, found)
            else:
                tool.GetNotes(item, found)
            for k in range(1, found.Length() + 1):
                attached[_entry(found.Value(k))].append(
                    (str(item.ToString().ToCString()), sub))
        notes = TDF_LabelSequence()
        tool.GetNotes(notes)
        out = []
        for i in range(1, notes.Length() + 1):
            label = notes.Value(i)
            comment = XCAFDoc_NoteComment.Get_s(label)
            out.append(Note(text=str(comment.Comment().ToExtString()),
                            user=str(comment.UserName().ToExtString()),
                            timestamp=str(comment.TimeStamp().ToExtString()),
                            items=tuple(attached.get(_entry(label), ()))))
        return out
    finally:
        app.Close(doc)
