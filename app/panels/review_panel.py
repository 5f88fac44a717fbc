"""The review queue (one panel per browser): the negatives the last training run mined (and the
false positives it queued for review alone), in its review order, one verdict each: background,
object of a class, wrong box, skip."""

from __future__ import annotations

import dataclasses

import viser

from factorydet_core.evaluation.diagnostics import num_points_in_box, patches_in_box, review_item_markdown
from factorydet_core.io.dataset import annotation_min_points
from factorydet_core.session.store import HIDE_LABELLED_IOU
from factorydet_core.session.world import expected_reach

from ..clients import ClientView
from . import from_user

ALL = "all"


@dataclasses.dataclass
class ReviewPanel:
    progress_text: viser.GuiMarkdownHandle
    progress: viser.GuiProgressBarHandle
    filter_class: viser.GuiDropdownHandle
    filter_frame: viser.GuiDropdownHandle
    pending_only: viser.GuiCheckboxHandle
    hide_labelled: viser.GuiCheckboxHandle
    dim: viser.GuiCheckboxHandle
    item: viser.GuiMarkdownHandle
    object_class: viser.GuiDropdownHandle
    buttons: dict[str, viser.GuiButtonHandle]
    suspects: viser.GuiMarkdownHandle
    reach: viser.GuiMarkdownHandle

    def refresh(self, view: ClientView) -> None:
        state = view.state
        if state.db is None:
            self.progress_text.content = "_No session: nothing to review._"
            return
        counts = state.db.review_progress()
        total = counts["total"]
        self.progress_text.content = (
            f"**{counts['reviewed']} of {total} reviewed** · background {counts['background']} · "
            f"object {counts['object']} · wrong box {counts['wrong_box']} · skipped {counts['skip']}"
            if total
            else "_No mined negatives yet: train a model in the Training panel, then review here._"
        )
        self.progress.value = 100.0 * counts["reviewed"] / total if total else 0.0
        queue = view.load_queue()
        self.reach.content = (reach_text(queue) + filters_text(view)) if total else ""
        item = view.current_item()
        if item is None:
            self.item.content = (
                f"{len(queue)} item(s) in this filter. Press **Next** to start."
                if queue
                else "_No items in this filter._"
            )
        else:
            ids = [q["id"] for q in queue]
            rank = ids.index(item["id"]) + 1 if item["id"] in ids else 0
            labels = state.db.labels(item["frame_index"])
            result, drawn_frame = view.drawn_result()
            shown = result is not None and drawn_frame == item["frame_index"]
            self.item.content = review_item_markdown(
                item,
                labels,
                rank,
                len(queue),
                num_points=num_points_in_box(result, item["box"]) if shown else None,
                min_points=annotation_min_points(state.dataset, default=None),
                hold=state.db.hold_score(item["run_id"]),
                best_view=view.best_view(item),
                pseudo=state.db.pseudo_label_score(item["run_id"]),
            )
            place = item.get("place_versions") or {}
            if len(place) > 1:
                frames = ", ".join(str(f + 1) for f in item["place_frames"])
                self.item.content += (
                    f"  \n**One place, {len(place)} items** (frames {frames}): the verdict answers them all"
                )
        for name, button in self.buttons.items():
            button.disabled = not queue and name not in ("find_suspects", "next_suspect")
        suspect = view.current_suspect()
        count = len(state.suspects)
        text = (
            f"**{count} suspect label(s)**: labels the shown model contradicts strongly."
            if count
            else ("_No suspect labels listed; **Find suspect labels** asks the shown model._")
        )
        if suspect is not None:
            text += (
                f"  \nNow: label #{suspect['label_id']} *{suspect['class_name']}* (frame "
                f"{suspect['frame_index'] + 1}): the model says **{suspect['predicted_class']}** "
                f"({suspect['predicted_probability']:.2f}), {suspect['label_probability']:.2f} for its "
                "class. Fix it in the Labels panel or go on."
            )
        self.suspects.content = text


def filters_text(view: ClientView) -> str:
    """A line naming the queue's filters that narrow or widen it from the defaults (their controls
    sit in a folded folder), or "" with none."""
    with view.lock:
        parts = [
            *([f"predicted {view.filter_class}"] if view.filter_class is not None else []),
            *([f"frame {view.filter_frame + 1}"] if view.filter_frame is not None else []),
            *(["items on labelled objects hidden"] if view.hide_labelled else []),
            *(["reviewed items too"] if not view.pending_only else []),
            *(["an entry per item, not per place"] if not view.group_places else []),
        ]
    return f"  \n_Filters: {', '.join(parts)}._" if parts else ""


REACH_TOP = 50
"""The review panel estimates how many objects its first this many pending entries hold."""


def reach_text(queue: list[dict]) -> str:
    """How many real objects the pending entries of the shown queue hold by the model's scores
    (``world.expected_reach``), and how many of them the first ``REACH_TOP`` do."""
    pending = [q for q in queue if q["verdict"] in (None, "skip")]
    if not pending:
        return "_Nothing pending in this filter._"
    top, total = expected_reach([q.get("place_chance", q["score"]) for q in pending], REACH_TOP)
    text = f"{len(pending)} pending; the model's scores expect about {total:.0f} of them to be objects"
    if len(pending) > REACH_TOP and total > 0:
        text += f", {top:.0f} ({top / total:.0%}) in the first {REACH_TOP}"
    return text + "."


def build_review_panel(view: ClientView, find_suspects=None) -> ReviewPanel:
    gui = view.client.gui
    state = view.state
    names = list(state.dataset.class_names)
    with gui.add_folder("Review queue", order=20):
        progress_text = gui.add_markdown("")
        progress = gui.add_progress_bar(0.0, animated=False)
        reach = gui.add_markdown("")
        item = gui.add_markdown("")
        object_class = gui.add_dropdown("Object class", names, initial_value=view.object_class)
        buttons = {
            "background": gui.add_button(
                "Background [B]",
                color="gray",
                hint="Confirmed negative: not an object, or a part or misplaced box of a labelled one",
            ),
            "object": gui.add_button("Object [O]", color="green", hint="A real object of the class above"),
            "wrong_box": gui.add_button(
                "Wrong box [R]",
                color="orange",
                hint="A real object with no label yet, but the segment is wrong",
            ),
            "skip": gui.add_button("Skip [X]"),
            "seen_best": gui.add_button(
                "Look where it is seen best [I]",
                hint="The frame whose points in the item's box are the most: an object mined where it "
                "shows a few points can be plain to see there; a verdict still answers the item",
            ),
            "previous": gui.add_button("Previous [P]"),
            "next": gui.add_button("Next [N]"),
        }
        # Folded by default: the item and its verdict keys fit above the fold, and the Labels
        # folder below comes sooner.
        with gui.add_folder("Filters", expand_by_default=False):
            filter_class = gui.add_dropdown("Predicted class", [ALL, *names], initial_value=ALL)
            frames = [ALL, *(str(i + 1) for i in range(state.dataset.num_frames))]
            filter_frame = gui.add_dropdown("Frame", frames, initial_value=ALL)
            pending_only = gui.add_checkbox("Pending only", initial_value=view.pending_only)
            hide_labelled = gui.add_checkbox(
                "Hide items on labelled objects",
                initial_value=view.hide_labelled,
                hint=f"Items whose box overlaps a label at IoU {HIDE_LABELLED_IOU} or more: parts, "
                "duplicates and loose boxes of labelled objects, trained as background whatever the "
                "verdict",
            )
            group_places = gui.add_checkbox(
                "One entry per place",
                initial_value=view.group_places,
                hint="An object mined in several frames (or twice in one) is one entry, and one verdict "
                "answers all its items; needs the frames placed in one world frame",
            )
            dim = gui.add_checkbox("Dim the scene", initial_value=view.dim)
            buttons["batch"] = gui.add_button(
                "Background for all pending in this filter", color="red", hint="One undoable edit"
            )
    with gui.add_folder("Suspect labels", order=21, expand_by_default=False):
        suspects = gui.add_markdown("")
        buttons["find_suspects"] = gui.add_button("Find suspect labels", hint="Runs in the background")
        buttons["next_suspect"] = gui.add_button("Next suspect [U]")
    panel = ReviewPanel(
        progress_text, progress, filter_class, filter_frame, pending_only, hide_labelled, dim, item,
        object_class, buttons, suspects, reach,
    )  # fmt: skip

    def set_filter(_event=None) -> None:
        with view.lock:
            view.filter_class = None if filter_class.value == ALL else filter_class.value
            view.filter_frame = None if filter_frame.value == ALL else int(filter_frame.value) - 1
            view.pending_only = bool(pending_only.value)
            view.hide_labelled = bool(hide_labelled.value)
            view.group_places = bool(group_places.value)
            view.dim = bool(dim.value)
            view.current_item_id = None
        view.step(0)

    for handle in (filter_class, filter_frame, pending_only, hide_labelled, group_places, dim):
        handle.on_update(lambda event: set_filter() if from_user(event) else None)

    view.class_dropdowns.append(object_class)

    @object_class.on_update
    def _(event: viser.GuiEvent) -> None:
        if from_user(event):
            view.set_object_class(object_class.value)

    buttons["background"].on_click(lambda _: view.verdict("background"))
    buttons["object"].on_click(lambda _: view.verdict("object", object_class.value))
    buttons["wrong_box"].on_click(lambda _: wrong_box(view))
    buttons["skip"].on_click(lambda _: view.verdict("skip"))
    buttons["seen_best"].on_click(lambda _: view.look_where_seen_best())
    buttons["previous"].on_click(lambda _: view.step(-1))
    buttons["next"].on_click(lambda _: view.step(1))
    buttons["batch"].on_click(lambda _: view.batch_verdict("background"))
    buttons["next_suspect"].on_click(lambda _: view.next_suspect())
    if find_suspects is not None:
        buttons["find_suspects"].on_click(
            lambda _: find_suspects() or view.notify("Suspect labels", "Busy: a job is running.")
        )
    return panel


def wrong_box(view: ClientView) -> None:
    """Mark the item a real object whose segment is wrong, stay on it, and select its points so
    that the person can box them right away (Label segment, or the Box fields after it)."""
    item = view.current_item()
    view.verdict("wrong_box", advance=False)
    if item is None:
        return
    # The patches inside the mined box in the shown cut (the app's cut may differ from the one
    # training mined from, so the stored patch ids are not used).
    result, drawn_frame = view.drawn_result()
    if result is not None and drawn_frame == item["frame_index"]:
        view.select_patches(patches_in_box(result, item["box"]))
        view.notify(
            "Wrong box",
            "Its points are selected: shift-click or shift-drag to add the rest of the object, then "
            "Label segment [L]; Next [N] goes on.",
        )
    else:  # looking at another frame (where it is seen best, say): nothing of the item's is drawn
        view.notify(
            "Wrong box",
            "Click the object's points in this frame (shift-click or shift-drag for more), then "
            "Label segment [L]; Next [N] goes on.",
        )
