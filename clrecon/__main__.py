from clrecon.cli import main

if __name__ == "__main__":  # not when a spawned process (the figure process) imports it
    raise SystemExit(main())
