"""Text about review items for the app's panels."""

from factorydet_core.evaluation.diagnostics import review_item_markdown

ITEM = {
    "id": 7,
    "frame_index": 2,
    "run_id": 1,
    "round": 0,
    "predicted_class": "box",
    "score": 0.42,
    "best_annotated_iou": 0.0,
    "box": [1.0, 2.0, 0.5, 1.0, 1.0, 1.0, 0.0],
    "patch_set": [3, 4],
    "probabilities": [0.1, 0.0, 0.6, 0.0, 0.0, 0.0, 0.0, 0.3],
}


def test_review_item_markdown_gives_the_points_in_the_box_and_the_annotation_policy():
    text = review_item_markdown(ITEM, [], 1, 5, num_points=37, min_points=50)
    assert "**Item 1 of 5** (#7, frame 3" in text
    assert "37 points in its box (the data set labels objects of at least 50 points)" in text
    assert "box 0.60" in text and "background 0.30" in text
    # A data set that states no policy, and a frame that is not drawn: no such claims.
    assert "(the data set labels" not in review_item_markdown(ITEM, [], 1, 5, num_points=37)
    assert "points in its box" not in review_item_markdown(ITEM, [], 1, 5)
    # The queue's current overlap with the labels, beside the one at mining time.
    assert "when mined 0.00, now 0.45" in review_item_markdown({**ITEM, "label_iou": 0.45}, [], 1, 5)
    assert ", now" not in text


def test_a_held_item_says_training_keeps_it_out_of_the_background_until_a_verdict():
    assert "**Held**: scored 0.35 or more" in review_item_markdown(ITEM, [], 1, 5, hold=0.35)
    assert "Held" not in review_item_markdown(ITEM, [], 1, 5, hold=0.5)  # below: background already
    assert "Held" not in review_item_markdown(ITEM, [], 1, 5)
    decided = {**ITEM, "verdict": "background", "verdict_class": None, "reviewer": "ann"}
    assert "Held" not in review_item_markdown(decided, [], 1, 5, hold=0.35)


def test_a_pseudo_labelled_item_says_training_takes_it_for_its_predicted_class_until_a_verdict():
    text = review_item_markdown(ITEM, [], 1, 5, hold=0.35, pseudo=0.4)
    assert "**Pseudo-label**: scored 0.4 or more off every label, so training takes it for a *box*" in text
    assert "Held" not in text
    # Below the pseudo-label score it is held; on a labelled object it is held, not a label.
    assert "**Held**" in review_item_markdown(ITEM, [], 1, 5, hold=0.35, pseudo=0.5)
    on_label = review_item_markdown({**ITEM, "label_iou": 0.5}, [], 1, 5, hold=0.35, pseudo=0.4)
    assert "Pseudo-label" not in on_label and "**Held**" in on_label
    decided = {**ITEM, "verdict": "object", "verdict_class": "box", "reviewer": "ann"}
    assert "Pseudo-label" not in review_item_markdown(decided, [], 1, 5, pseudo=0.4)


def test_an_item_queued_for_review_alone_says_training_leaves_it_out_until_a_verdict():
    alone = {**ITEM, "in_background": 0}
    assert "**For review alone**" in review_item_markdown(alone, [], 1, 5)
    assert "For review alone" not in review_item_markdown({**ITEM, "in_background": 1}, [], 1, 5)
    assert "For review alone" not in review_item_markdown(ITEM, [], 1, 5)  # a queue before schema 4
    decided = {**alone, "verdict": "background", "verdict_class": None, "reviewer": "ann"}
    assert "For review alone" not in review_item_markdown(decided, [], 1, 5)
    # Above the run's hold score it is still one for review alone, not a held mined negative.
    held = review_item_markdown({**alone, "score": 0.9}, [], 1, 5, hold=0.35)
    assert "For review alone" in held and "Held" not in held


def test_a_place_in_a_learned_order_says_its_chance_of_a_label_and_what_it_was_learned_from():
    text = review_item_markdown({**ITEM, "place_useful": 0.624, "learned_from": 40}, [], 1, 5)
    assert (
        "Learned order: a **62%** chance that a verdict here gives a label (fitted on 40 answered places)"
        in text
    )
    assert "Learned order" not in review_item_markdown(ITEM, [], 1, 5)
    # Too few answers yet: it says it follows the queue order, and until when.
    learning = review_item_markdown({**ITEM, "place_useful": None, "learned_from": 12}, [], 1, 5)
    assert "Learned order: the queue order until 20 places are answered" in learning
    assert "(it looks again every 10 verdicts)" in learning and "chance" not in learning


def test_an_item_seen_better_elsewhere_says_where_and_how_to_look():
    import numpy as np

    from factorydet_core.session.world import BestView

    view = BestView(frame_index=5, num_points=120, num_points_here=9, box=np.zeros(7))
    text = review_item_markdown(ITEM, [], 1, 5, best_view=view)
    assert "Seen best in frame 6: 120 points in its box there against 9 here" in text
    assert "Look where it is seen best [I]" in text
    assert "Seen best" not in review_item_markdown(ITEM, [], 1, 5)
