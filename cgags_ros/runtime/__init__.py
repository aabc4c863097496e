"""
The registration processes: typed jobs, the state that runs them, supervision.

:mod:`.jobs` names each kind of job and its answer, and adds up a tracked stream's counts;
:mod:`.process` holds the ``ChildSession`` that runs them and what they share, and the
process's side of the pipe; :mod:`.supervisor` runs them in a killable process;
:mod:`.checks` is the second lane, a tracked stream's periodic checks at a lower priority.
Importing these does not import the pipeline (Open3D).
"""
