"""Lightning training of the normal-flow head on simulated scenes (``evseg.train``).

- :mod:`~evseg.train.augment`: augmentation of event slices with their ground-truth flow;
- :mod:`~evseg.train.data`: shards of encoder features + GT, the LightningDataModule;
- :mod:`~evseg.train.module`: the LightningModule (losses, metrics, optimiser);
- :mod:`~evseg.train.cli`: LightningCLI (``python -m evseg.train fit --config ...``);
- :mod:`~evseg.train.evaluate`: flow accuracy on held-out scenes and real recordings.

``data``, ``module`` and ``cli`` import Lightning (the ``train`` extra); ``augment`` and
``evaluate`` need only the core dependencies.
"""
