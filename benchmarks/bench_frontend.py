"""mipslam bench --scenario frontend (options: --set frontend.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "frontend", *sys.argv[1:]]))
