"""The zoo's networks; importing this package registers them all."""

from zoo.nets import student  # noqa: F401
