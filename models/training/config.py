"""The configuration of a training run: one typed object for ``mateqa train`` and the flow.

``TrainConfig`` is what ``mateqa train STAGE`` builds from its options (``flows.cli`` derives
them from these fields) and what the ``train`` flow takes as its one parameter, so the
command, a deployment and the Python API cannot disagree on a knob or its default. Each field
says what it does and its range; unknown keys are refused.
"""

from __future__ import annotations

from typing import Annotated, Literal

from pydantic import BaseModel, ConfigDict, Field, field_validator

Stage = Literal["completion", "relations"]
Steps = Annotated[int, Field(ge=1, le=10_000_000)]
Rate = Annotated[float, Field(gt=0, le=1.0)]
GridSide = Annotated[int, Field(ge=8, le=512)]


class TrainConfig(BaseModel):
    """Everything a training run is given: what to train, on what corpus, for how long."""

    model_config = ConfigDict(extra="forbid", frozen=True)

    stages: list[Stage] = Field(
        default=["completion", "relations"], min_length=1,
        description="what to train, in order: the completion networks, then the relation "
        "networks on the same corpus (they read the completion network)")
    workspace: str = Field(
        default="train-workspace", min_length=1,
        description="training workspace: corpus, dataset, snapshots, reports, checkpoints")
    shared: str | None = Field(
        default=None, description="folder of real STEP parts added to the corpus (split by "
        "file: half of them held out whole); null: the generated library only")
    variants: int = Field(default=100, ge=0, le=100_000,
                          description="parametric variants per category of the sample library")
    seed: int = Field(default=0, ge=0, le=2**32 - 1, description="seed of variants and splits")
    pairs_per_relation: int = Field(
        default=150, ge=1, le=100_000,
        description="the corpus's pair scenes per relation (split by part)")
    contact_pairs: int = Field(
        default=0, ge=0, le=100_000, description="pair scenes of parts touching at random "
        "orientations, seldom a face mate (none by default: see the relation model card)")
    clearance_pairs: int = Field(
        default=0, ge=0, le=100_000, description="pair scenes of two parts on one axis 1.5 to "
        "4 mm apart, coaxial without a concentric mate (none by default)")
    workers: int | None = Field(
        default=None, ge=1, le=256,
        description="worker processes for CAD work and rendering; null: one per core")
    threads: int = Field(default=1, ge=1, le=256,
                         description="torch threads (one is fastest on a busy 2-core machine)")
    grids: tuple[GridSide, GridSide] = Field(
        default=(32, 64), description="completion input and output grid sides (the paper's "
        "64 256 is for a GPU, in its own workspace)")
    protocols: list[Literal["observed", "oracle-box"]] = Field(
        default=["observed", "oracle-box"], min_length=1,
        description="completion input protocols to train for")
    completion_methods: list[str] | None = Field(
        default=None, min_length=1, description="learned completion methods to train; null: "
        "every one the registry has (models.completions)")
    completion_steps: Steps = Field(default=2000,
                                    description="training steps per completion network")
    lr: Rate = Field(default=1e-3, description="Adam learning rate of the completion networks "
                     "(the paper's 1e-4 suits long GPU runs)")
    lr_critic: Rate = Field(default=1e-4, description="Adam learning rate of a critic")
    completion_out: str | None = Field(
        default=None, description="folder for the completion checkpoints and their card; null: "
        "WORKSPACE/checkpoints/completion (`mateqa ship completion` ships them)")
    relation_methods: list[str] | None = Field(
        default=None, min_length=1, description="relation networks to train; null: every one "
        "the registry has (models.relation_methods)")
    relation_inputs: list[str] | None = Field(
        default=None, min_length=1, description="relation inputs to train a network for; null: "
        "every trained input the registry has (models.relation_inputs)")
    relation_steps: Steps = Field(default=2000,
                                  description="training steps per relation network")
    relation_out: str | None = Field(
        default=None, description="folder for the relation checkpoints and their card; null: "
        "WORKSPACE/checkpoints/relations (`mateqa ship relations` ships them)")

    @field_validator("completion_methods")
    @classmethod
    def _completion_methods(cls, names: list[str] | None) -> list[str] | None:
        from models.completions import learned

        return _known(names, learned(), "learned completion method")

    @field_validator("relation_methods")
    @classmethod
    def _relation_methods(cls, names: list[str] | None) -> list[str] | None:
        from models.relation_methods import learned

        return _known(names, learned(), "relation network")

    @field_validator("relation_inputs")
    @classmethod
    def _relation_inputs(cls, names: list[str] | None) -> list[str] | None:
        from models.relation_inputs import trained

        return _known(names, trained(), "trained relation input")

    def methods_of_completion(self) -> list[str]:
        from models.completions import learned

        return list(self.completion_methods or learned())

    def methods_of_relations(self) -> list[str]:
        from models.relation_methods import learned

        return list(self.relation_methods or learned())

    def inputs_of_relations(self) -> list[str]:
        from models.relation_inputs import trained

        return list(self.relation_inputs or trained())


def _known(names: list[str] | None, known: tuple[str, ...], what: str) -> list[str] | None:
    unknown = [n for n in names or [] if n not in known]
    if unknown:
        raise ValueError(f"unknown {what} {unknown}; known: {', '.join(known)}")
    return names
