"""``python -m evseg.train fit --config configs/train/default.yaml`` (see :mod:`evseg.train.cli`)."""

from evseg.train.cli import main

if __name__ == "__main__":
    main()
