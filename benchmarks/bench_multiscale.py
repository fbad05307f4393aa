"""mipslam bench --scenario multiscale (options: --set multiscale.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "multiscale", *sys.argv[1:]]))
