"""mipslam bench --scenario frequency_loss (options: --set frequency_loss.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "frequency_loss", *sys.argv[1:]]))
