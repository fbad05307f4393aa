"""mipslam bench --scenario basin (options: --set basin.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "basin", *sys.argv[1:]]))
