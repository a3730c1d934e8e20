"""greyfit's Python entry points for other tools: `from greyfit.client import Client`."""
