"""HTTP service, job store, executors and CLI of greyfit: thin layers over `solvers`."""
