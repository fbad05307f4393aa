"""mipslam bench --scenario kill_resume (options: --set kill_resume.KEY=VALUE; mipslam bench --list-scenarios, docs/bench.md)."""
import sys
from mipslam.cli import main
sys.exit(main(["bench", "--scenario", "kill_resume", *sys.argv[1:]]))
