"""mipslam bench --scenario pgo (options: --set pgo.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "pgo", *sys.argv[1:]]))
