"""Workflows: every command's body, built on the library; ``capvector.cli`` is only their table.

- :mod:`~capvector.workflows.fit`: ``capvector fit|validate``, LightningCLI over the module and the
  data module, and the fit config other workflows parse
- :mod:`~capvector.workflows.recipe`: ``capvector recipe``, the whole recipe as resumable stages
- :mod:`~capvector.workflows.evaluate`: ``capvector evaluate``, MuJoCo rollouts of a checkpoint
- :mod:`~capvector.workflows.demos`: ``capvector demos``, scripted-expert demonstrations
- :mod:`~capvector.workflows.expert_success`: the scripted LIBERO expert's success table
- :mod:`~capvector.workflows.sweep`: ``capvector sweep-scale``, choosing the merge scale λ
- :mod:`~capvector.workflows.report`: ``capvector report``, success against steps of a recipe's arms
- :mod:`~capvector.workflows.vectors`: ``capvector extract|merge|compose``
- :mod:`~capvector.workflows.inspection`: ``capvector inspect``
- :mod:`~capvector.workflows.export`: ``capvector export|import-original``
- :mod:`~capvector.workflows.backbone_info`: ``capvector backbone-info``
- :mod:`~capvector.workflows.serve`: ``capvector serve``
- :mod:`~capvector.workflows.push`: ``capvector push``

The library (``module``, ``policy``, ``backbones``, ``callbacks``, ``objectives``, ``data``,
``vectors``, ``eval``, ``envs``) never imports from here.
"""
