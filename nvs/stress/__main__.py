"""python -m nvs.stress [--out results/stress.md] [--steps N] [--sections a,b]: see nvs.stress.report."""

from nvs.stress.report import main

if __name__ == "__main__":
    main()
