<?xml version="1.0" encoding="UTF-8"?>
<core:CityModel xmlns:core="http://www.opengis.net/citygml/2.0" xmlns:bldg="http://www.opengis.net/citygml/building/2.0" xmlns:app="http://www.opengis.net/citygml/appearance/2.0" xmlns:gml="http://www.opengis.net/gml">
<core:cityObjectMember>
<bldg:Building gml:id="b1">
<ade:owner xmlns:ade="urn:example:ade">Smith & Sons&nbsp;</ade:owner>
<bldg:lod2MultiSurface>
<gml:MultiSurface srsName="urn:ogc:def:crs:EPSG::25832" srsDimension="3">
<gml:surfaceMember>
<gml:Polygon gml:id="p0">
<gml:exterior>
<gml:LinearRing gml:id="r0">
<gml:posList>691000.0 5334000.0 520.0 691010.0 5334000.0 520.0 691010.0 5334010.0 520.0 691000.0 5334000.0 520.0</gml:posList>
</gml:LinearRing>
</gml:exterior>
</gml:Polygon>
</gml:surfaceMember>
<gml:surfaceMember>
<gml:Polygon gml:id="p1">
<gml:exterior>
<gml:LinearRing gml:id="r1">
<gml:posList>691000.0 5334000.0 520.0 691010.0 5334010.0 520.0 691000.0 5334010.0 520.0 691000.0 5334000.0 520.0</gml:posList>
</gml:LinearRing>
</gml:exterior>
</gml:Polygon>
</gml:surfaceMember>
</gml:MultiSurface>
</bldg:lod2MultiSurface>
</bldg:Building>
</core:cityObjectMember>

</core:CityModel>
