"""The task's contracts: metric names, the DataModule catalog, the prediction writers and the nets' base class."""

from __future__ import annotations

from pathlib import Path

import pytest

from zoo.callbacks import PredictionCsvWriter, PredictionTopicWriter
from zoo.catalog import CatalogSnapshot, SequenceCatalog, read_catalog
from zoo.metrics import NAMES, MetricKey, TrajectoryError, TrajectoryMetrics
from zoo.nets.base import TrajectoryNet
from zoo.registry import list_models, model_class
from zoo.task import TrajectoryTask


def test_metric_keys_give_the_names_results_tables_read():
    assert [MetricKey("val", None).logged_name(name) for name in NAMES] == ["val_Dx", "val_Dy", "val_Dz", "val_E",
                                                                            "val_RMSE"]
    assert MetricKey("val", None, "pseudo").logged_name("E") == "val_E_pseudo"
    assert MetricKey("test", "dark").logged_name("E") == "test_E_dark"
    assert MetricKey("test", "ideal", "pseudo").logged_name("RMSE") == "test_RMSE_pseudo_ideal"
    assert MetricKey("test", "ideal", "smooth").logged_name("E") == "test_E_smooth_ideal"
    assert len({MetricKey("test", light, ref).slot for light in ("ideal", "dark") for ref in ("gt", "pseudo")}) == 4
    assert TrajectoryError is TrajectoryMetrics  # the deprecated name still works


def test_a_run_without_a_catalog_gets_the_defaults():
    catalog = read_catalog(None)
    assert catalog == CatalogSnapshot() and catalog.sequence_ids == () and catalog.bev_bounds is None
    assert [catalog.test_light(i) for i in range(3)] == ["ideal", "dark", "2"]
    assert read_catalog(object()) == CatalogSnapshot()


class _Data:
    sequence_ids = ["a", "b"]
    sequence_paths = [Path("a.mcap"), Path("b.mcap")]
    test_lights = ["dark"]
    bev_bounds = [[0.0, 1.0], [2.0, 3.0]]


def test_a_catalog_is_read_once_into_a_snapshot():
    data = _Data()
    assert isinstance(data, SequenceCatalog)
    catalog = read_catalog(data)
    data.sequence_ids = ["changed"]
    assert catalog.sequence_ids == ("a", "b") and catalog.sequence_paths == (Path("a.mcap"), Path("b.mcap"))
    assert catalog.test_light(0) == "dark" and catalog.test_light(1) == "1" and catalog.bev_bounds == _Data.bev_bounds
    data.test_lights = []
    assert read_catalog(data).test_lights == ("ideal", "dark")


def test_the_task_adds_the_writers_its_output_settings_ask_for(tmp_path):
    assert TrajectoryTask("student").configure_callbacks() == []
    writers = TrajectoryTask("student", predictions_dir=str(tmp_path), predictions_topic="/p").configure_callbacks()
    assert [type(w) for w in writers] == [PredictionCsvWriter, PredictionTopicWriter]
    assert writers[0].output_dir == tmp_path and writers[1].topic == "/p"


@pytest.mark.parametrize("name", list_models())
def test_every_registered_net_follows_the_contract(name):
    cls = model_class(name)
    assert issubclass(cls, TrajectoryNet) and cls.model_name == name
    assert isinstance(cls.trains_position, bool) and callable(cls.set_bounds)


def test_a_net_with_nothing_to_train_has_no_objective():
    """srp_phat trains no position and has no auxiliary loss: validation (and Lightning's sanity check of
    ``aaute fit``) must skip its loss, not take the finite check of an integer 0."""
    import torch

    task = TrajectoryTask(net="srp_phat")
    assert not task.net.trains_position
    batch = {"gt": torch.zeros(2, 3), "gt_valid": torch.ones(2, dtype=torch.bool),
             "pseudo": torch.zeros(2, 3), "pseudo_valid": torch.ones(2, dtype=torch.bool)}
    total, terms = task.objective({"position": torch.ones(2, 3)}, batch)
    assert total is None and terms == {}
    trained = TrajectoryTask(net="student")
    total, _ = trained.objective({"position": torch.ones(2, 3, requires_grad=True)}, batch)
    assert torch.is_tensor(total) and total.item() > 0
