"""The application layer (roof floor): the one CLI, the ``fit`` / ``dub`` pipelines, ``eval``, the demo, and
corpus and training orchestration. It may import everything below it (``nvp`` core, ``tracking``,
``renderer``); nothing below imports it."""
