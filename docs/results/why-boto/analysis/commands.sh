# why-boto: the sweeps `botorl study run docs/results/why-boto/study.toml` runs, in its order (frozen commit bc5a976); the same by hand:
# block b0 (legacy: its results are its paired.csv)
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 200-207 --population-size 8 --out study/why-boto/b0/b  # (b) BOTO, alpha -1
botorl sweep --tasks pointmaze-medium --profile quick --methods wsrl --seeds 200-207 --population-size 8 --out study/why-boto/b0/a --set pretrained=study/why-boto/b0/b  # (a) WSRL
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 200-207 --population-size 8 --out study/why-boto/b0/d --set boto.noise=none pretrained=study/why-boto/b0/b  # (d) re-fit control (no noise)
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=1 --seeds 200-207 --population-size 8 --out study/why-boto/b0/c --set pretrained=study/why-boto/b0/b  # (c) BOTO, alpha +1
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 200-207 --population-size 8 --out study/why-boto/b0/e --set boto.backup_entropy=false pretrained=study/why-boto/b0/b  # (e) BOTO without the entropy term
botorl sweep --tasks pointmaze-medium --profile quick --methods wsrl --seeds 200-207 --population-size 8 --out study/why-boto/b0/f1 --set online_reseed=1 pretrained=study/why-boto/b0/b  # (f1) WSRL, online seed changed
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 200-207 --population-size 8 --out study/why-boto/b0/f2 --set online_reseed=1 pretrained=study/why-boto/b0/b  # (f2) BOTO alpha -1, online seed changed
# block b1 (legacy: its results are its paired.csv)
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 208-215 --population-size 8 --out study/why-boto/b1/b  # (b) BOTO, alpha -1
botorl sweep --tasks pointmaze-medium --profile quick --methods wsrl --seeds 208-215 --population-size 8 --out study/why-boto/b1/a --set pretrained=study/why-boto/b1/b  # (a) WSRL
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 208-215 --population-size 8 --out study/why-boto/b1/d --set boto.noise=none pretrained=study/why-boto/b1/b  # (d) re-fit control (no noise)
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=1 --seeds 208-215 --population-size 8 --out study/why-boto/b1/c --set pretrained=study/why-boto/b1/b  # (c) BOTO, alpha +1
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 208-215 --population-size 8 --out study/why-boto/b1/e --set boto.backup_entropy=false pretrained=study/why-boto/b1/b  # (e) BOTO without the entropy term
botorl sweep --tasks pointmaze-medium --profile quick --methods wsrl --seeds 208-215 --population-size 8 --out study/why-boto/b1/f1 --set online_reseed=1 pretrained=study/why-boto/b1/b  # (f1) WSRL, online seed changed
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 208-215 --population-size 8 --out study/why-boto/b1/f2 --set online_reseed=1 pretrained=study/why-boto/b1/b  # (f2) BOTO alpha -1, online seed changed
# block b2 (legacy: its results are its paired.csv)
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 216-223 --population-size 8 --out study/why-boto/b2/b  # (b) BOTO, alpha -1
botorl sweep --tasks pointmaze-medium --profile quick --methods wsrl --seeds 216-223 --population-size 8 --out study/why-boto/b2/a --set pretrained=study/why-boto/b2/b  # (a) WSRL
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 216-223 --population-size 8 --out study/why-boto/b2/d --set boto.noise=none pretrained=study/why-boto/b2/b  # (d) re-fit control (no noise)
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=1 --seeds 216-223 --population-size 8 --out study/why-boto/b2/c --set pretrained=study/why-boto/b2/b  # (c) BOTO, alpha +1
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 216-223 --population-size 8 --out study/why-boto/b2/e --set boto.backup_entropy=false pretrained=study/why-boto/b2/b  # (e) BOTO without the entropy term
botorl sweep --tasks pointmaze-medium --profile quick --methods wsrl --seeds 216-223 --population-size 8 --out study/why-boto/b2/f1 --set online_reseed=1 pretrained=study/why-boto/b2/b  # (f1) WSRL, online seed changed
botorl sweep --tasks pointmaze-medium --profile quick --methods boto --alphas=-1 --seeds 216-223 --population-size 8 --out study/why-boto/b2/f2 --set online_reseed=1 pretrained=study/why-boto/b2/b  # (f2) BOTO alpha -1, online seed changed
botorl study report docs/results/why-boto/study.toml
