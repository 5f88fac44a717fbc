"""Helpers every panel shares."""

from app.panels import short_name


def test_a_checkpoint_path_is_shortened_and_a_run_name_kept():
    assert short_name("/work/main/factorydet_core/models/default.pt") == "…/models/default.pt"
    assert short_name("C:\\models\\x\\m.pt") == "…/x/m.pt"
    assert short_name("run 2 (next) final") == "run 2 (next) final"
    assert short_name("models/m.pt") == "models/m.pt"


def test_the_review_panel_estimates_the_reach_of_the_first_pending_entries():
    from app.panels.review_panel import REACH_TOP, reach_text

    queue = [{"verdict": None, "score": 0.5, "place_chance": 0.75}] * 10
    queue += [{"verdict": "skip", "score": 0.1}] * (REACH_TOP + 10)  # a skip is still pending
    queue += [{"verdict": "background", "score": 0.9}] * 5  # decided: not counted
    text = reach_text(queue)
    # 10 x 0.75 + 60 x 0.1 = 13.5 expected; the first 50: 7.5 + 40 x 0.1 = 11.5 (85%).
    assert text.startswith(f"{10 + REACH_TOP + 10} pending; the model's scores expect about 14 of them")
    assert f"12 (85%) in the first {REACH_TOP}" in text
    assert reach_text(queue[:3]) == "3 pending; the model's scores expect about 2 of them to be objects."
    assert reach_text([{"verdict": "object", "score": 0.9}]) == "_Nothing pending in this filter._"


def test_the_review_panel_names_the_filters_its_folded_folder_sets():
    import threading
    from types import SimpleNamespace

    from app.panels.review_panel import filters_text

    view = SimpleNamespace(
        lock=threading.Lock(), filter_class=None, filter_frame=None, hide_labelled=False, pending_only=True,
        group_places=True,
    )  # fmt: skip
    assert filters_text(view) == ""  # the defaults: nothing said
    view.filter_class, view.filter_frame, view.hide_labelled = "cone", 2, True
    assert filters_text(view) == "  \n_Filters: predicted cone, frame 3, items on labelled objects hidden._"
    view.filter_class = view.filter_frame = None
    view.hide_labelled, view.pending_only = False, False
    assert filters_text(view) == "  \n_Filters: reviewed items too._"
    view.pending_only, view.group_places = True, False
    assert filters_text(view) == "  \n_Filters: an entry per item, not per place._"


def test_the_points_drawn_choices_read_back_as_the_budgets_they_show():
    from app.panels.display_panel import POINTS_DRAWN_CHOICES, points_drawn_label, points_drawn_value

    assert points_drawn_label(None) == "All" and points_drawn_label(20_000) == "20,000"
    for budget in (*POINTS_DRAWN_CHOICES, 12_345):
        assert points_drawn_value(points_drawn_label(budget)) == budget


def test_the_display_panel_offers_a_budget_set_elsewhere_in_its_order_and_sends_the_choice(small_dataset_dir):
    import viser

    from app.panels.display_panel import build_display_panel
    from app.state import AppState
    from factorydet_core.io.dataset import open_dataset

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        state = AppState(open_dataset(small_dataset_dir))
        panel = build_display_panel(server, state)
        assert panel.points_drawn.value == "All"
        state.set_display(points_drawn=12_345)  # e.g. another code path, or factorydet app --points-drawn
        panel.refresh(state)
        assert panel.points_drawn.value == "12,345"
        options = panel.points_drawn.options
        assert options.index("20,000") < options.index("12,345") < options.index("10,000")
        state.set_display(points_drawn=None)
        panel.refresh(state)
        assert panel.points_drawn.value == "All"
    finally:
        server.stop()


def test_the_display_panel_shows_the_floor_grid_setting_and_a_like_view_copies_it(small_dataset_dir):
    import viser

    from app.panels.display_panel import build_display_panel
    from app.state import AppState
    from factorydet_core.io.dataset import open_dataset

    server = viser.ViserServer(host="127.0.0.1", port=0, verbose=False)
    try:
        state = AppState(open_dataset(small_dataset_dir))
        panel = build_display_panel(server, state)
        assert state.show_grid and panel.show_grid.value
        state.set_display(show_grid=False)
        state.set_display(point_size=0.1)  # another setting leaves the grid as it is
        panel.refresh(state)
        assert not state.show_grid and not panel.show_grid.value
        like = state.shared.new_view(like=state)  # a view that starts like this one
        assert not like.show_grid and state.shared.new_view().show_grid
    finally:
        server.stop()


def test_the_app_command_takes_a_points_budget_of_at_least_one(capsys):
    import pytest

    from app.cli import build_app_parser

    assert build_app_parser().parse_args(["app", "--points-drawn", "20000"]).points_drawn == 20_000
    assert build_app_parser().parse_args(["app"]).points_drawn is None
    for bad in ("0", "-5", "many"):
        with pytest.raises(SystemExit):
            build_app_parser().parse_args(["app", "--points-drawn", bad])
    assert "--points-drawn" in capsys.readouterr().err
