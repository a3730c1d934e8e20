"""HTTP service, job store, executors and CLI of greyfit: thin layers over `solvers`.

Folders by concern: `http/` (the FastAPI edge), `jobs/` (store, dispatcher, executors, what a worker
runs), `cli/` (the `greyfit` command) and `report/` (report pages and figures); `settings`,
`metrics` and `task_kinds` (the one table of task kinds) are shared by all of them."""
