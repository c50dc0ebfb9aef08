"""The model zoo: networks, the Lightning task, smoothing, weights and the ``aaute`` command."""
