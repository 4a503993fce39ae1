"""The service's core, shared by the API (``app``) and the workers (``worker``): settings, the
database and its records, object storage, the model library, and the queue's names and Celery
factory. It imports neither ``app`` nor ``worker``, and builds nothing when imported."""
