"""``python -m pushtorch``: the experiment app (:mod:`pushtorch.apps.experiment`)."""

from pushtorch.apps.experiment import main

if __name__ == "__main__":
    main()
