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


def test_the_points_drawn_choices_read_back_as_the_budgets_they_show():
    from app.panels.display_panel import points_drawn_label, points_drawn_value
    from factorydet_core.colors import POINTS_DRAWN_CHOICES

    assert points_drawn_label(None) == "All" and points_drawn_label(20_000) == "20,000"
    for budget in (*POINTS_DRAWN_CHOICES, 12_345):
        assert points_drawn_value(points_drawn_label(budget)) == budget
