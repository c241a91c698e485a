"""Serving: a trained policy answers observations over openpi's websocket protocol, so a robot or a
simulator in another environment drives it with ``openpi_client.WebsocketClientPolicy``.

- :mod:`~capvector.serve.wire`: openpi's msgpack-numpy messages
- :mod:`~capvector.serve.schema`: the observation schema (our keys and openpi's LIBERO client's)
- :mod:`~capvector.serve.server`: ``PolicyServer``, the asyncio server that batches requests

``capvector serve`` (load once, device, precision, signals) is :mod:`capvector.workflows.serve`.
"""
