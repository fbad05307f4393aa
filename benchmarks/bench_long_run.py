"""mipslam bench --scenario long_run (options: --set long_run.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "long_run", *sys.argv[1:]]))
