"""The export room: predicted mates back into CAD.

For each assembly of a run, ``predictions`` pools the product's answers per pair beside the
CAD's (``AssemblyMates``, nothing dropped: every pair and the assembly carry a status);
``notes`` writes the assembly as an XBF document with OCCT XDE notes on its parts and pairs;
``sidecar`` writes the JSON (with its schema, ``mates.schema.json``) that names parts as the
STEP does and joints as Onshape, FreeCAD and Fusion 360 do; ``script`` writes a CadQuery
assembly script whose constraints are the predicted mates; ``job`` runs all three per assembly
in a crash-isolated worker.
"""
