"""mipslam bench --scenario render_speed (options: --set render_speed.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "render_speed", *sys.argv[1:]]))
