"""Cut the RINEX test fixtures of test/data/rinex/ from ../shared/data/rinex/.

    python tools/cut_rinex_fixtures.py [SHARED_RINEX_DIR]

Observation files: the header and the first epochs; navigation files: the header and the
records of the hours around them; SP3/CLK: the header and a few epochs.
"""
from __future__ import annotations

import gzip
import sys
from pathlib import Path

import hatanaka

ROOT = Path(__file__).resolve().parent.parent
OUT = ROOT / 'test' / 'data' / 'rinex'


def header_and_body(lines: list[str]) -> tuple[list[str], list[str]]:
    end = next(i for i, line in enumerate(lines) if 'END OF HEADER' in line)
    return lines[:end + 1], lines[end + 1:]


def first_epochs_v3(lines: list[str], n: int) -> list[str]:
    head, body = header_and_body(lines)
    starts = [i for i, line in enumerate(body) if line.startswith('>')]
    return head + body[:starts[n]]


def first_epochs_v2(lines: list[str], n: int, n_obs: int) -> list[str]:
    head, body = header_and_body(lines)
    i, per_sat = 0, -(-n_obs // 5)
    for _ in range(n):
        count = int(body[i][29:32])
        i += -(-count // 12) + count * per_sat
    return head + body[:i]


def nav_records_v3(lines: list[str], keep) -> list[str]:
    head, body = header_and_body(lines)
    out, i = list(head), 0
    while i < len(body):
        n = 4 if body[i][0] in 'RS' else 8
        if keep(body[i][4:17]):
            out += body[i:i + n]
        i += n
    return out


def nav_records_v2(lines: list[str], keep) -> list[str]:
    head, body = header_and_body(lines)
    out = list(head)
    for i in range(0, len(body), 8):
        if keep(body[i][3:14]):
            out += body[i:i + 8]
    return out


def write(name: str, lines: list[str]) -> None:
    text = '\n'.join(lines) + '\n'
    path = OUT / name
    if name.endswith('.crx.gz'):
        path.write_bytes(hatanaka.compress(text.encode('ascii'), compression='gz'))
    elif name.endswith('.gz'):
        path.write_bytes(gzip.compress(text.encode('ascii'), mtime=0))
    else:
        path.write_text(text)
    print(f'{path}: {path.stat().st_size} bytes')


def main(src: Path) -> None:
    OUT.mkdir(parents=True, exist_ok=True)
    slac = (src / 'slac' / 'slac1180.21o').read_text().splitlines()
    write('slac1180.21o', first_epochs_v2(slac, 6, 20))
    nav = (src / 'slac' / 'brdc1180.21n').read_text().splitlines()
    write('brdc1180.21n', nav_records_v2(nav, lambda t: t.split()[3] in ('16', '18', '20')))
    sp3 = (src / 'slac' / 'COD0MGXFIN_20211180000_01D_05M_ORB.SP3').read_text().splitlines()
    stars = [i for i, line in enumerate(sp3) if line.startswith('*')]
    # Epochs 18-21: 19:30-19:45, where the CLK file starts.
    write('COD0MGXFIN_20211180000_01D_05M_ORB.SP3',
          sp3[:stars[0]] + sp3[stars[18]:stars[22]] + ['EOF'])
    clk = (src / 'slac' / 'COD0MGXFIN_20211180000_01D_30S_CLK.CLK').read_text().splitlines()
    head, body = header_and_body(clk)
    write('COD0MGXFIN_20211180000_01D_30S_CLK.CLK',
          head + [line for line in body if line.startswith('AS G')
                  and line[24:30] in ('19 30 ', '19 35 ', '19 40 ', '19 45 ')])
    pdel = (src / 'pdel' / 'pdel0010.21o').read_text().splitlines()
    write('pdel0010.21o', first_epochs_v3(pdel, 4))
    cbw = gzip.decompress((src / 'pdel' / 'cbw10010.21n.gz').read_bytes()).decode()
    write('cbw10010.21n.gz', nav_records_v2(cbw.splitlines(),
                                            lambda t: t.split()[3] in ('0', '2', '23')))
    crx = hatanaka.decompress((src / 'nya1' / 'NYA100NOR_S_20241240000_01D_30S_MO.crx.gz')
                              .read_bytes()).decode()
    write('NYA100NOR_S_20241240000_01D_30S_MO.crx.gz', first_epochs_v3(crx.splitlines(), 4))
    for s in ('GN', 'EN', 'CN'):
        name = f'NYA100NOR_S_20241240000_01D_{s}.rnx.gz'
        text = gzip.decompress((src / 'nya1' / name).read_bytes()).decode()
        write(name, nav_records_v3(text.splitlines(),
                                   lambda t: t[:10] in ('2024 05 02', '2024 05 03')
                                   and int(t[11:13]) in (0, 1, 2, 23)))


if __name__ == '__main__':
    main(Path(sys.argv[1]) if len(sys.argv) > 1 else ROOT.parent / 'shared' / 'data' / 'rinex')
