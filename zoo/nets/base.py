"""The contract every zoo network follows.

A network is a plain ``nn.Module`` whose ``forward`` takes a dict of named input tensors (the
DataModule's batch keys, e.g. ``audio_mel`` B x C x H x W and ``image`` B x 3 x H x W) and returns a
dict with at least ``position`` (B x 3, metres); auxiliary heads add more keys. Class attributes
declare what it consumes (input name -> recipe of :mod:`datamodules.features`), its category in
the paper's table, and whether the position output is trained by regression (AV-FDTI decodes its
position from a heat map and trains only its auxiliary losses). ``auxiliary_losses`` returns the
net's own weighted loss terms given its outputs and the training targets; by default that is
``class_weight`` x the cross-entropy of a ``class_logits`` head (:func:`classification_loss`), if
the net has one. :meth:`TrajectoryNet.set_bounds` receives the data's bird's-eye area before a run;
only nets that search or decode a region (SRP-PHAT, the phase student, AV-FDTI) use it.

The class attribute ``inputs`` is the reference (the papers' recipes; profiling builds a default net,
so reference GMACs never change). A net built with ``input_recipes`` (e.g. ``{"image": "resnet64"}``,
a reduced-budget recipe of :mod:`datamodules.features`) reads other recipes of the same kind: the
instance attribute ``inputs`` holds the merged mapping, and :meth:`TrajectoryNet.input_shapes`,
:meth:`~TrajectoryNet.check_inputs` and :meth:`~TrajectoryNet.example_inputs` follow it, so data
made with another recipe still fails with an error naming the recipe the net expects. Only nets
whose encoders adapt to the size accept the argument (the image nets); their parameters are the
same at every size. :meth:`TrajectoryNet.reduced_settings` lists what departs from the reference,
for the captions of reduced-budget results.
"""

from __future__ import annotations

from collections.abc import Callable, Mapping
from typing import Any, ClassVar

import torch
from torch import nn

from datamodules.errors import ConfigError
from datamodules.features import image_recipe, mel_recipe, phase_recipe

NUM_CLASSES = 6  #: five drone types + "no drone" (AV-FDTI class convention)

#: input name -> the lookup of its recipe kind (raises ValueError listing the known recipes of that kind)
RECIPE_LOOKUPS: dict[str, Callable[[str], Any]] = {"audio_mel": mel_recipe, "audio_phase": phase_recipe,
                                                   "image": image_recipe}


class TrajectoryNet(nn.Module):
    """Base class of the zoo's networks (see the module docstring)."""

    model_name: ClassVar[str] = ""
    #: input name -> recipe; on the class: the reference recipes; on an instance: the ones it reads
    inputs: dict[str, str] = {}
    category: ClassVar[str] = "supervised"  #: 'supervised' or 'self-supervised' (the paper's table)
    #: False when the position is decoded, not regressed (AV-FDTI, SRP-PHAT): only auxiliary losses train it
    trains_position: ClassVar[bool] = True
    #: batch entries the net reads besides its inputs, when the batch has them (e.g. ``mic_positions``, ``time``)
    context_keys: ClassVar[tuple[str, ...]] = ()

    def __init__(self, in_channels: int = 4, class_weight: float = 0.0, input_recipes: dict[str, str] | None = None):
        super().__init__()
        self.in_channels = in_channels
        self.class_weight = class_weight
        self.inputs = self.resolve_input_recipes(input_recipes)

    @classmethod
    def resolve_input_recipes(cls, input_recipes: Mapping[str, str] | None) -> dict[str, str]:
        """The reference ``inputs`` with ``input_recipes`` merged over them, validated.

        Raises:
            ConfigError: an input the net does not declare, or a recipe unknown for that input's kind.
        """
        recipes = dict(cls.inputs)
        if input_recipes is None:
            return recipes
        if not isinstance(input_recipes, Mapping):
            raise ConfigError(f"{cls.model_name} input_recipes must map input name -> recipe name, "
                             f"got {input_recipes!r}")
        for name, recipe in input_recipes.items():
            if name not in recipes:
                raise ConfigError(f"{cls.model_name} has no input {name!r} to give a recipe to; "
                                 f"its inputs: {recipes}")
            try:
                RECIPE_LOOKUPS[name](recipe)
            except ValueError as error:
                raise ConfigError(f"{cls.model_name} input_recipes[{name!r}]: {error}") from None
            recipes[name] = recipe
        return recipes

    def reduced_settings(self) -> dict[str, str]:
        """Where this instance departs from the reference: setting -> "value (reference value)"; {} if nowhere."""
        reference = type(self).inputs
        return {f"inputs.{name}": f"{recipe} (reference {reference[name]})"
                for name, recipe in self.inputs.items() if recipe != reference[name]}

    def check_inputs(self, inputs: dict[str, torch.Tensor]) -> None:
        """Raise a ConfigError naming the input, recipe and shape when ``inputs`` do not fit."""
        for name, shape in self.input_shapes().items():
            expected = " x ".join(map(str, shape))
            if name not in inputs:
                raise ConfigError(f"{self.model_name} needs input {name!r} (recipe {self.inputs[name]!r}, "
                                 f"B x {expected}); got keys {sorted(inputs)}")
            got = tuple(inputs[name].shape)
            if got[1:] != shape:
                raise ConfigError(f"{self.model_name} needs {name} of shape B x {expected} "
                                 f"(recipe {self.inputs[name]!r}), got {got}")

    def input_shapes(self) -> dict[str, tuple[int, ...]]:
        """Per-sample shape of each input (without the batch axis), from this instance's recipes."""
        shapes: dict[str, tuple[int, ...]] = {}
        for name, recipe in self.inputs.items():
            if name == "audio_mel":
                shapes[name] = (self.in_channels, *mel_recipe(recipe).output_shape)
            elif name == "image":
                shapes[name] = (3, *image_recipe(recipe).size)
            elif name == "audio_phase":
                shapes[name] = phase_recipe(recipe).output_shape(self.in_channels)
        return shapes

    def example_inputs(self, batch_size: int = 1) -> dict[str, torch.Tensor]:
        """Random inputs of this instance's shapes (a default net: the reference shapes, for profiling)."""
        generator = torch.Generator().manual_seed(0)
        return {name: torch.rand(batch_size, *shape, generator=generator) * (2 if name == "image" else 1)
                - (1 if name == "image" else 0) for name, shape in self.input_shapes().items()}

    def set_bounds(self, bounds: list[list[float]] | torch.Tensor) -> None:
        """Take the data's bird's-eye area [[x_min, x_max], [y_min, y_max]] (m); by default it is not used."""

    def auxiliary_losses(
        self, outputs: dict[str, torch.Tensor], batch: dict[str, torch.Tensor], target: torch.Tensor,
        target_valid: torch.Tensor,
    ) -> dict[str, torch.Tensor]:
        """Weighted auxiliary loss terms (name -> scalar); ``target`` is the training position target."""
        if self.class_weight > 0 and "class_logits" in outputs and "class_id" in batch:
            return {"class": self.class_weight * classification_loss(outputs["class_logits"], batch["class_id"])}
        return {}


def classification_loss(logits: torch.Tensor, class_id: torch.Tensor) -> torch.Tensor:
    """Cross-entropy over samples with a known class (class id -1 is ignored)."""
    known = class_id >= 0
    if not known.any():
        return logits.sum() * 0.0
    return nn.functional.cross_entropy(logits[known], class_id[known])
