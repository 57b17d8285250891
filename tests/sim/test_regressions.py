"""Every seed on which the simulator found a bug, replayed after its fix,
under the command's own hash seed.  A fix's own unit test sits beside the
code it fixed where one can be written; this replays the whole run that
found it."""

from __future__ import annotations

import os
import re
import subprocess
import sys

import pytest
from support import ROOT, unmeasured

#: A profile's options, and seed -> what went wrong before the fix.
FOUND: list[tuple[tuple[str, ...], dict[int, str]]] = [
    (("--robots", "3", "--tasks", "10", "--faults", "mixed"), {
        2: "a robot gave up waiting for a dead teammate's plan before it could find it down: it decided alone",
        32: "an older plan answered late was taken for a restart: a live teammate declared down, the cluster split",
        50: "the same as seed 2, a kill alone on a lossy link",
        65: "the same as seed 32, after a kill: the survivors disagreed on every later task",
        76: "the same as seed 32, with the feeder starved",
        100: "the same as seed 2, with the robot's own loop starved",
        478: "a burst of loss swallowed every retransmission of one robot's statistics: the whole run failed",
        2067: "a robot killed again soon after its restart: its new process could not be found down within "
              "the readmission grace, and its teammates decided nothing",
        2144: "the same as seed 2067, with its loop starved",
        3548: "the same as seed 2067, with a teammate's loop starved",
        3868: "the same as seed 2067",
        8344: "the same as seed 2067",
        9308: "the same as seed 2067",
        5571: "two robots back at the same task: the one that admitted the other before taking the team's "
              "membership lost that admission and named an older epoch",
        3606: "the same as seed 5571: a task picked by both robots",
        3963: "the same as seed 5571",
        4513: "the same as seed 5571",
        5964: "the same as seed 5571",
        7315: "the same as seed 5571: three tasks picked twice",
        3291: "a retransmitted task post of a killed robot reached its restarted process, which took it as its "
              "own task: picked there and again where it went round",
        4156: "a robot killed again soon after its restart and restarted once more just after the feeder posted "
              "its join: the post reached no process, the teammates admitted it anyway and decided nothing while "
              "they waited for its plan",
        4389: "the same as seed 4156",
        4786: "the same as seed 4156",
        3531: "the three robots restarted in turn, each before the one before had joined: no process that decided "
              "the task before the join was left, the joiners could not join and decided nothing, and the task "
              "that no robot decided was lost",
    }),
    (("--robots", "6", "--tasks", "12", "--faults", "mixed", "--strategy", "compute-and-communicate"), {
        49: "the leader's decision was lost in a burst and never sent again: the follower decided nothing",
        50: "a follower stamped the leader's decision with its own, older membership epoch",
        71: "a robot restarted before the feeder ever heard from its old process: the feeder waited for the old "
            "process's decision for good",
        140: "the same as seed 71, with a partition and a starved loop",
        202: "the same as seed 71, with a freeze",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "kill,freeze,partition,loss=0.2"), {
        148: "a lost answer: one robot found no live holder of a module and decided the task for nobody, "
             "its teammates gave it to a robot",
        343: "the same as seed 148, after a partition healed",
        396: "the same as seed 148, a plan that did not arrive",
        419: "the same as seed 148, right after a partition",
        488: "the same as seed 148, after a kill",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "mixed", "--writes", "20"), {
        81: "a restarted robot's only co-holder of a module died before the first anti-entropy round: an "
            "acknowledged write was lost",
        266: "the same as seed 81",
        430: "the same as seed 148 of the lossy profile, on a run that also wrote",
        99: "a robot that took a teammate's decision kept its older membership: after the next join it named "
            "an epoch behind its teammates' on every task",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "mixed,swarm", "--writes", "20"), {
        204: "a robot frozen for 20 s in a pick, the one the places are read from: its teammates settled a task "
             "unavailable without it; back, it decided the task alone on its own knowledge and picked it",
        55: "a robot waiting for its teammates' decision gave up the moment before one, back from a partition, "
            "decided on knowledge: the two decided differently",
        1076: "a robot frozen 16 s, the only holder of the places: a teammate settling a task without it asked it "
              "once, the ask ran out past the deadline, and it decided nobody while the frozen one, back, decided "
              "on knowledge and the third took that",
        1453: "the same as seed 1076, after the feeder and the frozen robot were cut off",
        1534: "the same as seed 1076, and the teammate declared the frozen robot down a second after its "
              "notifications came again (the helper's answer of the indirect probe lost)",
        1535: "the same as seed 1076, with the feeder cut off meanwhile",
        1621: "a robot killed again before it took its join was named to its co-joiner and not to its teammate: "
              "the co-joiner admitted it in one more epoch, and named an epoch ahead of its teammate's on every task",
        356: "a robot cut off from everyone, whose observation of a teammate never started, left that teammate "
             "out once the partition healed, alone: its epoch, ahead of theirs, voided the majority's decision; "
             "later, with the first repair at 0.2 s: the feeder found it down and posted the next task without "
             "it, its teammates (who never did) waited 68 s for its plan on that task, and no task boundary "
             "came to take it back at",
        2271: "the holder the places are read from, frozen 20 s just after it decided a task on knowledge: a "
              "teammate that settled without it decided nothing once it found it down, the other had taken its "
              "decision; the task is now decided again on the next holder's knowledge",
        2619: "the same as seed 2271, frozen 17 s in a pick: both teammates decided nothing against its decision",
        1162: "a holder restarted empty 0.25 s before its only co-holder was killed, its first catch-up lost: two "
              "acknowledged writes gone with the last memory that held them (no data folders), now excused",
        3296: "the holder the places are read from frozen, then killed: both teammates decided again on the next "
              "holder, whose answers were lost to one of them; it decided nothing while the other decided on "
              "knowledge",
        3619: "a robot picked task 1 and was killed; its teammates, deciding late, skipped it as picked by that "
              "robot at task 1, then gave it task 2: its one job done was counted against task 2, never executed",
        3866: "the feeder, cut off from the start, never observed a robot its teammates went on counting: it "
              "could not tell that robot's answering process from a new one, never took it back, and its "
              "teammates waited for its plan on every later task",
        7862: "a starved robot settling a task ended on both teammates' unavailable answers, one of them 15 s old "
              "(its round waited on the teammate cut off): that one had decided again on the next holder since",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "mixed,crash,forge,swarm", "--writes", "20", "--storage"), {
        11774: "a robot back from a 16 s freeze decided a task in the membership it had left; a teammate had "
               "excluded it meanwhile, and the third, lagging, took the frozen one's decision: two epochs",
        15717: "a robot that had left a dead teammate out found the other, back from a partition, down after the "
               "heal, and decided nothing on every later task without asking it once: nobody was up to ask",
        18055: "a robot's waiting facts were due by one rule and not yet by another, by rounding: its knowledge "
               "writer spun while the simulated clock stood still, and the run never ended",
        20326: "a co-joiner of task 7 died after it took the post and started again: a starved teammate that "
               "took the post later admitted its new process, never given the post, and waited 120 s for its plan",
        21011: "the last task, posted only to the survivors while Robot2 was frozen, went to Robot2, whose "
               "teammates still granted it; the feeder took it back without the post, and it was never executed",
        27361: "Robot2 killed holding tasks 7 and 9 and back as a new process while the feeder was cut off; "
               "past the last task there was no task to join at, so its old tasks never went round again",
        43737: "the holder of the Location KB, frozen 4-24 s and declared down by both teammates, found them "
               "still settling the task it held, decided it on its own knowledge, and they settled it unavailable",
        50486: "a robot starved from the start took its teammates' decisions, first observed one after its "
               "restart, and waited for the new process's plan of the task before, 137 s by a timeout set while starved",
        50615: "a joiner admitted its co-joiner, which never took its post and was named to no teammate, then "
               "left it out again: two epochs ahead of its teammate on every task, and back two on taking its decision",
        54749: "a robot picked its task and died in a power cut a moment later; its decision was void, the survivor "
               "settled the task unavailable, and the record gave the pick to nobody",
        55904: "the same as seed 54749, on lossy links",
        63111: "a power cut took a robot as the run ended and started it again: the feeder's download of its "
               "statistics found nobody there and gave the run up",
        65327: "a robot picked its task and died with its granter in a power cut; the survivor decided the task "
               "again without them: a pick the record gives to another, excused as the cut's, listed",
        54708: "a robot without the knowledge found its one live teammate, cut off with the decision, down in the "
               "round that asked it, counted it as failed although that left it outnumbered, and decided alone",
        90301: "a robot cut off for 17 s, left out, asked a member about a slow teammate; the member, with no "
               "plan of it, left that teammate out alone on the word of a robot outside its membership, and the "
               "majority split in two",
        103234: "two robots back from a power cut joined at one task; the survivor that showed one of them its "
                "decision died before the other, starved, read it: that one started a fresh membership, the other "
                "was in the survivor's, and the two decided on in two epochs",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "mixed,swarm", "--writes", "60"), {
        40: "the same as seed 1076 of the 20-write profile, on lossy links: a robot cut off in a pick",
    }),
    (("--robots", "6", "--tasks", "12", "--faults", "mixed,swarm", "--strategy", "compute-and-communicate"), {
        21881: "a follower kept its leader down after the leader's cut healed while no task came; its restarted "
               "teammate joined and followed the leader, and the follower, no longer alone, decided the next task "
               "without it, though the leader's decision in its own membership had come",
        1623: "a follower whose observation of its leader was lost took the restarted leader's first state for "
              "the old process's, and waited 20 s for its decision on a task the new process was never given: it "
              "decided nothing",
        1162: "a cluster's three robots killed and restarted in turn, the last back only after the last task: "
              "it never joined, so the task nobody decided never went round again",
        2118: "a follower cut off while picking first observed its leader in a stale answer (an older plan of "
              "the process it had heard of) and took it for a restart: it left the leader out, in an epoch that "
              "went back when it adopted the leader's next decision",
        1045: "the same as seed 2118",
        2026: "a follower whose leader was found down decided the task itself, leaving the leader out, while "
              "the other follower had the leader's decision: one task in two epochs, and an epoch that went back",
        14580: "both followers decided alone once the restarted leader was named; one, frozen while it "
               "computed, used the leader's last plan the other had done without, asking it in vain: one task "
               "in two epochs",
        3005: "the leader took the post, was killed and restarted: its followers, which had never observed its "
              "old process, waited for its decision until they gave the task up",
        3229: "the same as seed 3005, the restarted leader then cut off from its followers",
        5822: "the same as seed 3005; once the followers decided alone, one that held the leader's last plan "
              "decided in its epoch and died, the other in the next: the feeder kept the dead one's decision",
    }),
    (("--robots", "9", "--tasks", "100", "--faults", "freeze,partition"), {
        20005: "a robot cut off dropped a task under its fence; granted again once the partition healed, it was "
               "settled, but the state showing the dropped task was never kept: the task never went round again",
        20001: "the feeder, cut off from every robot for 10 s, declared all nine down and gave the run up",
        20052: "the same as seed 20001, cut off twice",
        20060: "the same as seed 20001",
        20035: "a robot cut off from its cluster found both teammates down and decided tasks alone at once, while "
               "they went on counting it and gave it tasks (excused then: no finding may be excused here)",
        20046: "the same as seed 20035",
    }),
    (("--robots", "9", "--tasks", "40", "--faults", "freeze,partition"), {
        20025: "a robot that had declared both teammates down while it was cut off decided every task alone after "
               "the heal, while they counted it and assigned it tasks it never executed (excused then: no finding "
               "may be excused here)",
        20056: "the same as seed 20025",
    }),
    (("--robots", "9", "--tasks", "90", "--faults", "freeze,partition"), {
        20017: "a robot back from a freeze, still granted, was settled: the object it did not find, shown only in "
               "the state read then, was never recorded, and the task stayed assigned, never executed",
    }),
    (("--robots", "9", "--tasks", "30", "--faults", "freeze,partition,swarm", "--writes", "20"), {
        1891: "the feeder, settling a robot it had found down but its teammates still granted, waited on one "
              "observation whose server had dropped it while the feeder was cut off: 480 s, the run's settling "
              "461 s after the last task was decided",
    }),
    (("--robots", "9", "--tasks", "30", "--faults", "freeze,partition,swarm"), {
        116: "two robots whose observations failed at the start never had a third's first plan; it decided task 1 "
             "and, cut off, asked for its lease; one of them had taken the post but decided nothing yet and "
             "granted by the membership alone, then left it out of task 1, which it picked",
        2716: "a robot cut off for 3.5 s, alone, counted again on a teammate that had it down; with the third "
              "robot frozen, each left another out in an epoch 1 of its own",
        9188: "a robot that left a revived teammate out, and had the third down, asked the left-out one for "
              "its lease of a later task; never fed that task, it said 'not yet' for good and the cluster never "
              "finished",
        4246: "the oracle: a robot back from a cut counted a live teammate down on the requests that had failed "
              "during it and left it out alone; the split, a false suspicion of a robot cut off, was not excused "
              "as no error named the teammate",
        6028: "a robot cut off at the start was left out and never learned it; deciding on in a membership of "
              "its own, it left out another member once that one was cut off, in an epoch 1 of its own",
        16092: "the same as seed 6028, the last member alone without a majority",
        53530: "a robot that had promised, at its first task, to go on without a teammate's plans was cut off, "
               "left out and fed again; its teammates had taken that one back meanwhile, and on the old promise "
               "the robot left it out again at its first task after the join, in an epoch of its own",
        21652: "the same as seed 16092",
        27897: "a robot frozen through the task its teammates left it out of decided nothing there, so the "
               "feeder never took it back; once another member froze, the last one had no majority",
        30143: "a robot frozen while it decided, left out and taken back, then decided its old task (its "
               "teammates' decision gave it the job) and picked it after the task had gone round again",
        33136: "the same as seed 30143, a robot cut off",
        33489: "the same as seed 30143",
    }),
    # Judged alone, one restart is no median: the bound is the anti-entropy
    # round's (a missing catch-up, not one exchange lost at 10 % loss), and
    # the reads answered meanwhile are the point.
    (("--robots", "3", "--tasks", "10", "--faults", "kill,loss=0.1", "--writes", "20", "--catch-up-within", "5"), {
        59: "a restarted holder, its catch-up from one co-holder lost once, answered a teammate registering on "
            "/kb/facts/Object before it had caught up: a read while it lacked four acknowledged values",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "kill,freeze,partition,loss=0.2", "--writes", "10"), {
        112: "a robot whose read of the place failed asked its teammate for its decision three times, all "
             "three asks were lost, and it decided the task for nobody",
    }),
    (("--robots", "9", "--tasks", "30", "--faults", "mixed,crash,forge,swarm", "--writes", "20", "--storage"), {
        2: "a power cut of a module's holders and a freeze left every robot of cluster 2 down for 15 s: the "
           "feeder gave the run up at its next task instead of waiting for one to come back",
        5: "a robot killed by a power cut, then by its own kill: its journal torn twice, and the power cut's "
           "restart and its own each started a process, the second refused as the folder was in use",
        49: "the same as seed 5, the journal torn twice into a corrupt file that refused both starts",
        40: "the oracle: a power cut aimed at a robot of cluster 1 took two robots of cluster 3, whose split "
            "decision it did not excuse (the excuse looked only at the robot the cut was aimed at)",
        337: "a joiner took a post naming a co-joiner that missed its own (killed again, then cut off): it "
             "waited 91 s for that one's plan and the feeder gave the run up at 120 s",
        467: "the same as seed 337, the feeder's repeat saying the co-joiner missed its join come before the "
             "joiner had admitted it: forgotten, the joiner waited for good",
        728: "the same as seed 2, the feeder starved: a restart told while it took robots back made the last "
             "robot of the cluster down after its wait, and it gave the run up",
        770: "the same as seed 728",
        110: "a robot whose teammate and next-cluster holder of a module were both killed for good (and the "
             "robot that pushed to it too, one in each cluster) never had that module's later writes again",
        1114: "a joiner cut off from the one survivor of its cluster (its observation's retransmissions lost "
              "through the partition and after it) started a fresh membership without it after 20 s, while its "
              "co-joiner had joined in the survivor's: two memberships, and its epoch went back when it took "
              "the co-joiner's decision",
        3024: "the same as seed 54749 of three robots: a pick done before a power cut, given to nobody by the record",
        5563: "two robots of a cluster restarted by a power cut, one cut off: the other's restart came while the "
              "task was posted to the first as a joiner, so it was named to nobody; the joiner, which had never "
              "seen its old process, took the new one for the member and waited for its plan for good",
        4496: "a robot cut off for 20 s found both teammates down once the partition healed and counted on one "
              "again when it answered, though that one had gone on without it: the two left the third out in an "
              "epoch 1 of their own, while the third decided in the majority's epoch 1",
        6043: "the oracle: a robot killed, then a power cut that took a second robot of its three, left no "
              "majority; the survivor decided a task again without the last plan the cut took, and the split "
              "was not excused (the excuse counted the cut's kills only)",
        6294: "a robot restarted by a power cut took its join, but requests sent before its new process listened "
              "had counted it down; the feeder took it back as a member and fed it from its old process's task, "
              "which it refused",
    }),
    (("--robots", "3", "--tasks", "30", "--faults", "rejoin,loss,swarm"), {
        58: "a joiner cut off at its restart found its teammates had decided its join task without a plan of it "
            "(a repeat skipped on its claim), took them for past its join, and started a membership of its own, "
            "alone, without the claims: it gave an object again",
        143: "the same as seed 58",
        96: "a joiner left out while cut off started a membership of its own, alone, at an epoch of the task's "
            "number: the feeder took it for the newest and voided its teammates' decisions, and each task the lone "
            "robot dropped under its fence went round again after they had picked it",
        126: "the same as seed 96",
        420: "a joiner cut off until after a teammate's restart never saw its old process: it took the new one "
             "for the member it joined with, and waited for its plan for good",
        999: "the same as seed 420",
        314: "two robots restarted and cut off in turn: the second, left out by the survivor, started a membership "
             "naming its co-joiner, which had joined the survivor's; a majority to the feeder, the cluster split",
        902: "the same as seed 314",
        1567: "a robot that died between two tasks and restarted cut off was found down only by the wait for its "
              "plan, a request timeout later; the other teammate died meanwhile, and the survivor, outnumbered, "
              "decided nothing",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "mixed,late,hedge,swarm", "--writes", "20"), {
        261: "a delete tried again reached its holder restarted without a data folder, whose catch-up answer was "
             "held back: it removed nothing there, and the value stayed on the other holders",
        28: "a try of a post naming a member restarted, held back and taken after that member's new process had "
            "joined: the robot counted the new process gone and left it out alone, an epoch ahead",
        4608: "a try of a teammate's question about a frozen robot's plan, held back past the next tasks, was "
              "answered without the plan an earlier try had been shown: the robot asked left the frozen one out, "
              "the asker counted it in",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "mixed,late,swarm", "--writes", "20"), {
        686: "a teammate's question about a restarted robot's plan before its join, held back on the way, was "
             "answered after the join: the robot asked promised to go on without the new process's plans and "
             "left it out alone, one epoch ahead of the cluster",
        1046: "the same as seed 686",
        1158: "the same as seed 686",
        1308: "two tries of one question about a frozen teammate's plan, the first answered without it and the "
              "second with it (it came between): the asker counted the teammate in, the robot asked had promised "
              "to leave it out, and did",
    }),
    (("--robots", "3", "--tasks", "10", "--faults", "mixed,bounce,swarm", "--writes", "20"), {
        580: "a DELETE DATA tried again reached a holder started again 0.09 s after its kill, whose catch-up "
             "outlasted the 3 s a write waits for it (a co-holder starved, lossy links): it removed nothing there, "
             "was answered 2.04, and the value stayed on the others",
    }),
    (("--robots", "3", "--tasks", "30", "--faults", "bounce,late=0.2,swarm", "--writes", "60"), {
        46: "a robot kept in memory wrote under its lives' one name without a fence: its last life's push, held "
            "back past its restart, took the next life's dot at one holder, and the holders split at one version",
        79: "a holder restarted had the add from its peer's catch-up answer, not yet the delete, when that peer, "
            "the last to hold the delete, was killed: the value back, excused as a lost last copy",
    }),
]


#: Profiles whose seeds must not even have a finding excused by their
#: schedules: a split decision there was a protocol bug the excuse hid (a
#: robot cut off from its cluster deciding alone once the partition healed).
NONE_EXCUSED = {
    ("--robots", "9", "--tasks", "100", "--faults", "freeze,partition"),
    ("--robots", "9", "--tasks", "40", "--faults", "freeze,partition"),
}


@pytest.mark.parametrize(("profile", "seeds"), FOUND, ids=lambda v: " ".join(v) if isinstance(v, tuple) else "")
def test_every_seed_that_found_a_bug_now_holds_every_invariant(profile: tuple[str, ...], seeds: dict[int, str]) -> None:
    env = {**os.environ, "PYTHONHASHSEED": "0"}
    result = subprocess.run(
        [sys.executable, "-m", "coapkb", "sim", *profile, "--seeds", ",".join(map(str, sorted(seeds))), "--quiet"],
        capture_output=True, text=True, cwd=ROOT, timeout=600, env=unmeasured(env) if len(seeds) > 1 else env,
    )
    assert result.returncode == 0, result.stdout + result.stderr
    runs = f"{len(seeds)} run" + ("" if len(seeds) == 1 else "s")
    assert re.search(rf"^sim: {runs}, 0 violations, ", result.stdout, re.M), result.stdout
    if profile in NONE_EXCUSED:
        assert "excused" not in result.stdout, result.stdout
