"""The HTTP edge: the FastAPI app, its routes, authentication, body parsing and limits, the
problem+json answers and the OpenAPI description. It hands work to `greyfit.service.jobs` and never
runs numerics itself. Importing the package imports nothing (the client reads some of its modules)."""
