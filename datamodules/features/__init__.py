"""Input recipes of the zoo's models, one module per recipe family; every name is importable from here.

- :mod:`~datamodules.features.mel`: mel spectrograms (recipes A and B), the offline front end and its per-frame
  pieces;
- :mod:`~datamodules.features.incremental`: the streaming twin of the mel front end (each STFT frame of a stream
  computed once), equal to :func:`mel_features` on the same samples;
- :mod:`~datamodules.features.incremental_phase`: the streaming twin of the phase recipe (each frame's
  cross-spectra once, the causal static mean folded as audio arrives), equal to :class:`PhaseWindows`;
- :mod:`~datamodules.features.image`: camera image recipes and the darkness protocols;
- :mod:`~datamodules.features.phase`: GCC-PHAT phase features of every microphone pair;
- :mod:`~datamodules.features.clock_calibration`: the audio nodes' clock offsets estimated from the audio itself.
"""

from datamodules.features.image import (
    DARK_MODES,
    IMAGE_RECIPES,
    PUBLISHED_DARK_VALUE,
    ImageRecipe,
    image_features,
    image_recipe,
    published_dark,
    scale_image,
)
from datamodules.features.incremental import IncrementalMel
from datamodules.features.incremental_phase import IncrementalPhase
from datamodules.features.mel import (
    MEL_RECIPES,
    MelRecipe,
    audio_window,
    final_resize,
    frame_power_mel,
    mel_features,
    mel_frame_layout,
    mel_map,
    mel_recipe,
    stored_recipe,
)
from datamodules.features.phase import (
    PHASE_RECIPES,
    SPEED_OF_SOUND,
    GccPhat,
    PhaseRecipe,
    PhaseWindows,
    correct_cross_spectra,
    mic_pairs,
    pair_indices,
    phase_features,
    phase_recipe,
    split_frames,
)

__all__ = [
    "DARK_MODES",
    "IMAGE_RECIPES",
    "MEL_RECIPES",
    "PHASE_RECIPES",
    "PUBLISHED_DARK_VALUE",
    "SPEED_OF_SOUND",
    "GccPhat",
    "ImageRecipe",
    "IncrementalMel",
    "IncrementalPhase",
    "MelRecipe",
    "PhaseRecipe",
    "PhaseWindows",
    "audio_window",
    "correct_cross_spectra",
    "final_resize",
    "frame_power_mel",
    "image_features",
    "image_recipe",
    "mel_features",
    "mel_frame_layout",
    "mel_map",
    "mel_recipe",
    "mic_pairs",
    "pair_indices",
    "phase_features",
    "phase_recipe",
    "published_dark",
    "scale_image",
    "split_frames",
    "stored_recipe",
]
