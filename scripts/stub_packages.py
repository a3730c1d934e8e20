"""Empty package folders for every package pyproject.toml lists: the container image installs the
dependencies on these stubs first, so that layer survives changes to the source."""
import pathlib

import tomllib

setuptools = tomllib.loads(pathlib.Path("pyproject.toml").read_text())["tool"]["setuptools"]
folders = setuptools["package-dir"]
for package in setuptools["packages"]:
    head, _, rest = package.partition(".")
    top = f"{head}.{rest.split('.')[0]}" if rest else head
    tail = rest.split(".")[1:] if rest else []
    folder = pathlib.Path(folders[top], *tail)
    folder.mkdir(parents=True, exist_ok=True)
    (folder / "__init__.py").touch()
