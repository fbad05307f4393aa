"""mipslam bench --scenario aliasing (options: --set aliasing.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "aliasing", *sys.argv[1:]]))
