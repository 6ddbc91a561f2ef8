"""The robot agent: flies a committed policy with its own belief filter and reports its missions."""
