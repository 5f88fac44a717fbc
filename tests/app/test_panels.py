"""Helpers every panel shares."""

from app.panels import short_name


def test_a_checkpoint_path_is_shortened_and_a_run_name_kept():
    assert short_name("/work/main/factorydet_core/models/default.pt") == "…/models/default.pt"
    assert short_name("C:\\models\\x\\m.pt") == "…/x/m.pt"
    assert short_name("run 2 (next) final") == "run 2 (next) final"
    assert short_name("models/m.pt") == "models/m.pt"
