"""Named pretrained weights: the registry, the cache, and loading them into a ready net or task.

``load_pretrained(model, weights=...)`` returns the net in eval mode; ``weights`` is a registered
name (``"sim_quick"`` or ``"student.sim_quick"``) or the path of a weights file. The jobs are split
as timm splits them, each module importing only those listed before it:

- :mod:`zoo.weights.files`: safe reading, the three kinds of file, strict load with a readable
  diff, sha256 of a file;
- :mod:`zoo.weights.hub`: the cache folder, offline mode, download with the sha256 checked;
- :mod:`zoo.weights.registry`: :class:`Weights` entries, :data:`BUILTIN_WEIGHTS` and the local
  ``registry.json``;
- :mod:`zoo.weights.build`: resolving a name or path, building the net or task, writing
  self-describing weights files;
- :mod:`zoo.weights.converters`: the original authors' checkpoint layouts (``aaute import-checkpoint``),
  imported on its own.

Every public name of those modules but the converters' is importable from here.
"""

from zoo.weights.build import (
    build_net,
    load_pretrained,
    load_task,
    resolve_weights,
    save_weights_file,
    task_arguments,
    weights_file,
)
from zoo.weights.files import (
    SHOWN,
    WEIGHTS_FORMAT,
    WEIGHTS_VERSION,
    CheckpointContents,
    CheckpointError,
    UnsafeCheckpointError,
    WeightsMismatchError,
    file_sha256,
    load_state_checked,
    parse_contents,
    read_checkpoint,
    read_file,
    shape_text,
    state_differences,
)
from zoo.weights.hub import URL_SCHEMES, WeightsError, cached_file, is_url, offline_mode, weights_dir
from zoo.weights.registry import (
    BUILTIN_WEIGHTS,
    REGISTRY_FILE,
    Weights,
    all_weights,
    get_weights,
    list_weights,
    register_weights,
)

__all__ = [
    "BUILTIN_WEIGHTS",
    "REGISTRY_FILE",
    "SHOWN",
    "URL_SCHEMES",
    "WEIGHTS_FORMAT",
    "WEIGHTS_VERSION",
    "CheckpointContents",
    "CheckpointError",
    "UnsafeCheckpointError",
    "Weights",
    "WeightsError",
    "WeightsMismatchError",
    "all_weights",
    "build_net",
    "cached_file",
    "file_sha256",
    "get_weights",
    "is_url",
    "list_weights",
    "load_pretrained",
    "load_state_checked",
    "load_task",
    "offline_mode",
    "parse_contents",
    "read_checkpoint",
    "read_file",
    "register_weights",
    "resolve_weights",
    "save_weights_file",
    "shape_text",
    "state_differences",
    "task_arguments",
    "weights_dir",
    "weights_file",
]
