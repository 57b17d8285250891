"""Deliveries in a task list (coapkb.feeder.tasks): ``restock OBJECT``
lines, the deliveries ``coapkb team --tasks N`` puts before each repeat,
how a list with them is shared between clusters, and the task post that
says an object was restocked."""

from __future__ import annotations

from pathlib import Path

import cbor2
import pytest

from coapkb.feeder import FeederError, read_tasks_file, split_tasks, task_post
from coapkb.feeder.restock import shelf_places
from coapkb.feeder.tasks import Restock, task_count, with_restocks
from coapkb.kb.live import LiveKB
from coapkb.kb.named_updates import PROLOGUE, pick_update, restock_update
from coapkb.kb.store import KnowledgeBase

ONTOLOGIES = Path(__file__).resolve().parents[2] / "ontologies"


def test_a_tasks_file_takes_restock_lines(tmp_path: Path) -> None:
    path = tmp_path / "tasks.txt"
    path.write_text("Gucci_bag_14\n# a comment\nrestock Gucci_bag_14   # returned\n\nGucci_bag_14\n", encoding="utf-8")
    assert read_tasks_file(path) == ["Gucci_bag_14", Restock("Gucci_bag_14"), "Gucci_bag_14"]
    path.write_text("restock\n", encoding="utf-8")
    with pytest.raises(FeederError, match="restock OBJECT"):
        read_tasks_file(path)
    path.write_text("restock two names\n", encoding="utf-8")
    with pytest.raises(FeederError, match=r"tasks\.txt: 'restock two names'"):
        read_tasks_file(path)


def test_a_drawn_list_restocks_each_object_before_it_comes_round_again() -> None:
    drawn = ["A_1", "B_2", "C_3", "B_2", "A_1", "B_2"]
    assert with_restocks(drawn) == ["A_1", "B_2", "C_3", Restock("B_2"), "B_2", Restock("A_1"), "A_1",
                                    Restock("B_2"), "B_2"]
    assert task_count(with_restocks(drawn)) == 6
    assert with_restocks(["A_1", "B_2"]) == ["A_1", "B_2"]


def test_shares_count_tasks_and_a_delivery_goes_with_the_task_after_it() -> None:
    tasks = ["A_1", "B_2", Restock("A_1"), "A_1", "C_3", Restock("C_3")]
    assert split_tasks(tasks, 2) == [["A_1", "B_2"], [Restock("A_1"), "A_1", "C_3", Restock("C_3")]]
    assert split_tasks(tasks, 1) == [tasks]
    plain = [f"O_{i}" for i in range(7)]
    assert split_tasks(plain, 3) == [plain[0:2], plain[2:5], plain[5:7]]  # as before deliveries existed


def test_the_post_of_a_restocked_object_says_so() -> None:
    assert cbor2.loads(task_post(4, "A_1", restocked=True).payload) == {"seq": 4, "object": "A_1", "restocked": True}
    assert "restocked" not in cbor2.loads(task_post(4, "A_1").payload)


def test_a_delivery_puts_a_picked_object_back_on_its_shelf_in_the_kb() -> None:
    """The update the feeder writes, applied to a writable Location KB after
    the robot's own pick update: the shelf the files give, no pick left."""

    base = KnowledgeBase.load([ONTOLOGIES / "Location.owl"])
    place = shelf_places(base)["Gucci_bag_14"]
    kb = LiveKB(base, "R.1", wall_ms=lambda: 1)
    kb.update(PROLOGUE["Location"] + pick_update("Gucci_bag_14", "Robot2", 1))
    assert _pick_place(kb)["picked_by"] == "Robot2"
    kb.update(PROLOGUE["Location"] + restock_update("Gucci_bag_14", *place))
    row = _pick_place(kb)
    assert (int(row["aisle_no"]), int(row["rack_no"]), int(row["bin_no"])) == place
    assert row.get("picked_by") is None and row.get("picked_task") is None


def _pick_place(kb: LiveKB) -> dict:
    from coapkb.kb.named_queries import NAMED_QUERIES

    [row] = kb.query(NAMED_QUERIES["pick-place"].render({"name": "Gucci_bag_14"})).as_dicts()
    return {k: (None if v is None else str(v)) for k, v in row.items()}
