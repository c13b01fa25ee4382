"""Repository-relative locations built from the package location, never the working directory."""

from pathlib import Path

REPO_ROOT = Path(__file__).resolve().parents[2]  # harness/core/paths.py -> the repository
CONF_DIR = REPO_ROOT / "conf"
MJCF_DIR = REPO_ROOT / "models" / "mjcf"  # the vehicle model files the plant loads
