"""The feeder: the team's task source, a role of the system like a robot.

It posts each cluster's tasks in order (``POST /tasks``, :mod:`.tasks`),
waits for every robot's decision on the ``/robot/outcome`` it observes, and
keeps the team whole while robots fail: a robot that stops answering is
down and fed no more, a restarted one joins at a task boundary, one back
before its teammates noticed is fed what it missed, and a down robot's
unexecuted tasks go round again once it is fenced off (:mod:`.membership`,
:mod:`.fence`).

Used by the harness (:mod:`coapkb.harness.team`), which also starts the
robots, and by ``coapkb feed`` for robots started by hand
(:mod:`.team_folder`).  Security, discovery and the robots' access policy
know the feeder by its member name, :data:`~.security.FEEDER_IDENTITY`.
"""

from .channel import FeederSettings
from .feeder import Feeder, FeedOutcome
from .record import FateCounts, TaskRecord
from .roster import Roster
from .security import FEEDER_IDENTITY, feeder_security
from .tasks import FeederError, read_tasks_file, split_tasks, task_post

__all__ = [
    "FEEDER_IDENTITY",
    "FateCounts",
    "FeedOutcome",
    "Feeder",
    "FeederError",
    "FeederSettings",
    "Roster",
    "TaskRecord",
    "feeder_security",
    "read_tasks_file",
    "split_tasks",
    "task_post",
]
