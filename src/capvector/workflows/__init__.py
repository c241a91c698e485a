"""Workflows built on the training core: what users run, not what training needs.

- :mod:`~capvector.workflows.fit`: ``capvector fit|validate|test|predict``, LightningCLI over the
  module and the data module, and the fit config other workflows parse
- :mod:`~capvector.workflows.recipe`: ``capvector recipe``, the whole recipe as resumable stages
- :mod:`~capvector.workflows.evaluate`: ``capvector evaluate``, MuJoCo rollouts of a checkpoint
- :mod:`~capvector.workflows.sweep`: ``capvector sweep-scale``, choosing the merge scale λ
- :mod:`~capvector.workflows.report`: ``capvector report``, success against steps of a recipe's arms

The training core (``module``, ``backbones``, ``callbacks``, ``objectives``, ``data``, ``vectors``)
never imports from here.
"""
