"""The zoo's networks; importing this package registers them all."""

from zoo.nets import (
    asdnet,  # noqa: F401
    audionet,  # noqa: F401
    avfdti,  # noqa: F401
    avped,  # noqa: F401
    darknet,  # noqa: F401
    phase,  # noqa: F401
    student,  # noqa: F401
    visualnet,  # noqa: F401
    voranet,  # noqa: F401
)
