"""Relation evidence: a pair of parts in one view, and what its points say of their mates.

``pairs`` assembles every view of every labelled pair of a capture with its truth and the
inputs the relation methods read; ``pair_features`` measures the pair's evidence (contact
region, planes, axes, dominant directions) with the CAD mates fitted by ``fits``;
``cad_samples`` samples a placed part's CAD surface with the exact normals of its faces.
"""
