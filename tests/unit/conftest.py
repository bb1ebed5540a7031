import os
import sys

# robot_facts.py and other test helpers live next to the tests
sys.path.insert(0, os.path.dirname(__file__))
# tests run from the repository root, whatever the caller's folder
os.chdir(os.path.dirname(os.path.dirname(os.path.dirname(os.path.abspath(__file__)))))
