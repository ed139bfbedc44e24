"""The paper's experiments and their reports (paper, Experimental Results).

:mod:`~pushtorch.experiments.registry` names them: each experiment (``experiment=<name>``, a config in
``conf/experiment/``) and each part a suite runs. The steps they share are gathered in
:mod:`~pushtorch.experiments.common`, the outputs they write in :mod:`~pushtorch.experiments.report`.
"""
