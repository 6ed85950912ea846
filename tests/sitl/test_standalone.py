"""The emulator is a standalone PX4 look-alike: no module of ``sitl`` imports the mission runner
(layers go one way: the mission runner uses the emulator through its hooks, never back)."""

import pkgutil
import subprocess
import sys

import sitl

CHECK = """
import importlib, sys

class NoMissionRunner:
    def find_spec(self, name, path=None, target=None):
        if name == "mission_runner" or name.startswith("mission_runner."):
            raise ImportError(f"sitl imported {name}")

sys.meta_path.insert(0, NoMissionRunner())
for name in sys.argv[1:]:
    importlib.import_module(name)
"""


def test_no_sitl_module_imports_the_mission_runner() -> None:
    modules = ["sitl"] + [
        f"sitl.{info.name}"
        for info in pkgutil.iter_modules(sitl.__path__)
        if info.name != "__main__"
    ]
    assert len(modules) > 10  # the check saw the package
    done = subprocess.run(
        [sys.executable, "-c", CHECK, *modules], capture_output=True, text=True, check=False
    )
    assert done.returncode == 0, done.stderr


def test_the_emulator_command_starts_without_the_mission_runner() -> None:
    done = subprocess.run(
        [sys.executable, "-c", CHECK + "\nfrom sitl.cli import main\nmain(['--help'])", "sitl"],
        capture_output=True,
        text=True,
        check=False,
    )
    assert done.returncode == 0, done.stderr
    assert "--vehicles" in done.stdout
