"""mipslam bench --scenario loop_closure (options: --set loop_closure.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "loop_closure", *sys.argv[1:]]))
