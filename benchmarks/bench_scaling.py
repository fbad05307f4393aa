"""mipslam bench --scenario scaling (options: --set scaling.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "scaling", *sys.argv[1:]]))
