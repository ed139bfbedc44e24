"""The apps: command lines that compose a Hydra config and call the library with plain arguments.

``experiment`` (``python -m pushtorch``: the paper's experiments and the quickstart), ``simulate``
(``pushtorch-simulate``: simulated pushes into resumable shards), ``train`` (a model from push
records), ``predict`` (``pushtorch-predict``: predictions from a trained model), ``collect``
(a sweep's results as one table); beside them ``cli`` (the run folder, its lock and the one-line errors every
app shares) and ``config_check`` (the configs' schema, checked before a run folder is made). Apps import the
library; the library never imports an app (the import contracts in ``pyproject.toml``).
"""
