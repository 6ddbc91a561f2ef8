"""The robot agent: runs a committed policy with its own belief filter (issue 4)."""
