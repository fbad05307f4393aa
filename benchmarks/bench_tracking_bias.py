"""mipslam bench --scenario tracking_bias (options: --set tracking_bias.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "tracking_bias", *sys.argv[1:]]))
