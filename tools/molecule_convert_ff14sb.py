#!/usr/bin/env python3
"""Convert OpenMM's amber14/protein.ff14SB.xml into haptree's compact text table (data/molecules/ff14sb.dat).

Usage: /usr/bin/python3 tools/molecule_convert_ff14sb.py [path/to/protein.ff14SB.xml] > data/molecules/ff14sb.dat
Default input: the file shipped by Debian's python3-simtk (OpenMM 7.7). Standard library only (xml.etree).

Output format (one record per line, whitespace separated, '#' comments):
  scale14 <coulomb14scale> <lj14scale>
  type <type-name> <class> <element> <mass_amu> <sigma_nm> <epsilon_kJmol>
  residue <name> / atom <name> <type> <charge_e> / bond <a> <b> / external <a> / end
  proper <t1> <t2> <t3> <t4> <nterms> (<periodicity> <phase_rad> <k_kJmol>)*   ('*' = wildcard type)
Proper lines keep the XML file order (OpenMM's matching rule depends on it).
"""
import sys, os, xml.etree.ElementTree as ET

src = sys.argv[1] if len(sys.argv) > 1 else '/usr/lib/python3/dist-packages/openmm/app/data/amber14/protein.ff14SB.xml'
root = ET.parse(src).getroot()
out = sys.stdout
out.write('# haptree force-field table converted from OpenMM 7.7 amber14/protein.ff14SB.xml\n')
out.write('# by tools/molecule_convert_ff14sb.py. Parameters: AMBER ff14SB (Maier et al., J. Chem. Theory Comput. 11:3696, 2015).\n')
out.write('# The OpenMM XML file is distributed under the MIT licence:\n')
out.write('#   Copyright 2006-2021, Stanford University, Simbios and the Authors (Debian copyright file). Permission is\n')
out.write('#   hereby granted, free of charge, to any person obtaining a copy of this software and associated files, to deal in the\n')
out.write('#   Software without restriction (MIT/Expat licence; full text: /usr/share/doc/python3-simtk/copyright on Debian).\n')
out.write('# Units: nm, kJ/mol, e, amu, rad.\n')
nb = root.find('NonbondedForce')
out.write('scale14 %s %s\n' % (nb.get('coulomb14scale'), nb.get('lj14scale')))
lj = {a.get('type'): (a.get('sigma'), a.get('epsilon')) for a in nb.findall('Atom')}
for t in root.find('AtomTypes').findall('Type'):
    s, e = lj[t.get('name')]
    out.write('type %s %s %s %s %s %s\n' % (t.get('name'), t.get('class'), t.get('element'), t.get('mass'), s, e))
for r in root.find('Residues').findall('Residue'):
    out.write('residue %s\n' % r.get('name'))
    for a in r.findall('Atom'):
        out.write('atom %s %s %s\n' % (a.get('name'), a.get('type'), a.get('charge')))
    for b in r.findall('Bond'):
        out.write('bond %s %s\n' % (b.get('atomName1'), b.get('atomName2')))
    for b in r.findall('ExternalBond'):
        out.write('external %s\n' % b.get('atomName'))
    out.write('end\n')
tor = root.find('PeriodicTorsionForce')
for p in tor.findall('Proper'):
    if p.get('type1') is None:
        raise SystemExit('class-based Proper entries are not supported by this converter')
    ts = [p.get('type%d' % i) or '*' for i in range(1, 5)]
    terms = []
    i = 1
    while p.get('periodicity%d' % i) is not None:
        terms.append((p.get('periodicity%d' % i), p.get('phase%d' % i), p.get('k%d' % i)))
        i += 1
    out.write('proper %s %d %s\n' % (' '.join(ts), len(terms), ' '.join(' '.join(t) for t in terms)))
