import json, sys, time, warnings
warnings.simplefilter("ignore")
import rwwarp as rw
fields = [tuple(x) for x in json.load(open("/tmp/fields10.json"))]
n = int(sys.argv[1]) if len(sys.argv) > 1 else len(fields)
lens = rw.load_lens("a489_doe")
t = time.perf_counter()
m = rw.psf_map(lens, fields[:n], [0.45, 0.55, 0.65], size=32, device="cpu")
dt = time.perf_counter() - t
print(rw.__file__, "map %d x 3: %.1f s, %.2f PSF/s" % (n, dt, 3 * n / dt))
